"""Structured Gauss-Newton / Levenberg-Marquardt on the closed-form residual Jacobian.

Both minimise C = ||r||^2 over the free variables (see `oneshot_jax._sensitivity` for r
and its Jacobian by forward sensitivities, the forward twin of eq. (17) and (20)). They
share everything but the globalisation, which each concrete solver supplies:
`GaussNewton` backtracks along the projected step, `LevenbergMarquardt` adapts its
damping (Nielsen's rule).

Each is the wiring of a descent and a search. The descent is the linearisation's step
(`_linearisation`: the Jacobian dense, or matrix-free with conjugate gradients,
`linear_solver="cg"`, chosen by "auto" above `_strategy.MATRIX_FREE_MIN_THETA` free entries
of theta; the x0 blocks of each trajectory eliminated by a Schur complement,
`_linalg.eliminate_x0`, at a cost linear in the number of trajectories). The search
(`_search`) owns its state: `Backtracking` (Gauss-Newton) or `NielsenDamping` (LM: mu,
nu). The loop below, shared by both, handles bounds and the stopping tests.

Where the Jacobian has few columns per trajectory (at most `TRIAL_COLUMNS` free entries of
theta and of one x0, formed densely), forming it costs about what simulating the model
costs: a step then linearises at its trial point, whose loss is that linearisation's C,
and an accepted full step keeps it as the next iterate's linearisation, so a step costs
one pass over the records instead of two (the iterates are the same in exact
arithmetic).

Bounds and projections: each iterate is projected (a box is clipped), and entries at a
bound whose gradient points outwards are held for the step (an active set). Under a box,
entries that the clip stops short of their step move to their bound, and the others take
the step of the damped linear model with that move made, unless the plain clipped step
is better (`_descent`). A step that
fails (one that the projection clipped can predict no decrease at any damping) is
followed by a projected scaled-gradient step with an Armijo search along the projection
arc (`_gradient_arc`; Kanzow, Yamashita and Fukushima 2004), which decreases C at every
point that is not stationary. So a bound never stops the fit short of a solution.
A box on x0 (`fit(x0_bounds=...)`) is treated alike: each iterate's x0 is clipped into
it, and its entries at a bound whose gradient points outwards, or that the clip leaves
where they were, are held for the step (`AbstractLinearisation.holding_x0`).

Stopping (`oneshot_jax._optimality`): the fit converges (succeeds) when the first-order
measure at the current iterate, the scaled projected gradient, is at most `gtol`, or
when it stops for lack of progress (no step decreases C at round-off, or the optional step
test fired) with the measure at most its round-off limit 10 sqrt(eps) (a loss known
to relative precision eps resolves cosines down to about sqrt(eps) only, so a slowly
converging fit can stop a little above gtol = 1e-8; raised where the outputs are so far
above the residuals that their precision moves the cosines more,
`_optimality.stall_limit`; a column that vanished along the
fit, at a degenerate minimum, is measured there at the largest norm it had:
`_optimality.stall_test`); it
is `zero_residual` (success) when it can make no further progress with the loss at the
round-off level of the data (also after an accepted step below round-off of the scaled
parameters, ||D s|| <= eps ||D p||, where the loss keeps falling by round-off). Where
theta's columns of J, with the x0 columns eliminated, are rank deficient (an
over-parameterised model, a network in theta), it is
`statistically_converged` (success) when an accepted step, its predicted decrease confirmed
by the actual one, moved the fit by at most `stol` standard errors
(`_optimality.standard_errors`; the first-order test is not reached there). Where they
have full rank and no step decreases C at its round-off (a stall, or a failed search)
with the measure above its round-off limit, it is `statistically_converged` too when the
undamped Gauss-Newton step from that point is at most `stol` standard errors (`_settled`:
an output offset of 1e4 around a noise of 1e-3 leaves the loss too few digits to confirm
a decrease of 1e-12 of it, and Levenberg-Marquardt stopped there at 5e-5 standard errors
from the optimum with the measure 7.5e-7). Every
other stop is a failure that names its test:
`stalled` when no step decreases C while the linear model's predicted decrease is at
round-off (MINPACK's ftol test at machine epsilon) or the step is at the round-off
level of the parameters, or when the optional step test fired (rtol, atol: an accepted
step with ||D s|| <= rtol ||D p|| + atol and a decrease <= rtol C + atol, D =
sqrt(diag(J^T J))) with the measure above its round-off limit; `no_progress` when LM's
damping passes 1e20 or GN's backtracking 2^-30 and the gradient step fails too;
`max_steps_reached`.
A penalty enters as residuals sqrt(lambda h / T): lambda h must be non-negative, and the
solver stops with `RESULTS.negative_penalty` (reporting the true loss) when it is not.
"""

import abc
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._linalg import floor
from .._optimality import (
    SAME_PATH,
    Measures,
    data_scale,
    lazy_cond,
    n_observations,
    output_norm,
    stall_limit,
    standard_errors,
    vanished_columns,
    zero_residual,
)
from .._problem import Params
from .._results import RESULTS
from .._strategy import (
    LINEAR_SOLVERS,
    ParallelInTime,
    as_strategy,
    dense_jacobian_fits,
    least_squares_solver,
)
from ._linearisation import AbstractLinearisation, linearise, placeholder
from ._search import AbstractSearch
from .base import AbstractSolver, check_options, is_real

# The most Jacobian columns per trajectory (free entries of theta and of one x0) for which
# a step linearises at its trial point (`AbstractLeastSquares._linearises_trials`).
TRIAL_COLUMNS = 16


class LSQState(NamedTuple):
    blocks: AbstractLinearisation  # the linearisation at the current iterate
    loss: jax.Array  # C at the current iterate
    h_min: jax.Array  # the smallest lambda h(x_k) at the current iterate
    search: Any  # the search's state (LM's damping mu, nu)
    scale: jax.Array  # the loss of predicting zero outputs (`_optimality.data_scale`)
    measures: Measures  # the first-order measure here, the last step and its prediction
    done: jax.Array
    result: RESULTS
    primed: jax.Array  # whether `blocks` hold the linearisation (after the first step)
    top: Params  # the largest diag(J^T J) of each column so far (`_optimality.stall_test`)


class _Move(NamedTuple):
    """A step's move before the linearisation at its end (`AbstractLeastSquares._move`)."""

    params: Params  # the next iterate (the current one where nothing was taken)
    loss: jax.Array  # C there
    take: jax.Array  # whether the iterate moved (a linearisation is due there)
    h: Params  # the descent step
    pred: jax.Array  # the decrease the linear model predicts for the projected step
    gave_up: jax.Array  # the search gave up and the gradient step failed too
    search: Any  # the search's next state
    at_full: jax.Array  # whether the iterate moved to the full step's point
    # a step the search accepted against the linearisation's C but that did not decrease
    # the simulated loss, and no gradient step either: a stall at round-off
    same_path_reject: jax.Array


def _statistical_off(stol):
    """Whether `stol` switches the statistical test off: 0 given as a number (a traced
    stol, `traced_options`, is never 0)."""
    return isinstance(stol, (int, float, np.integer, np.floating)) and not stol


def _pushed_out(x, g, lower, upper):
    """Entries at a bound of their box that the gradient g pushes outwards (the active
    set of a box)."""
    return ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))


class AbstractLeastSquares(AbstractSolver):
    """The structured least-squares loop: the descent is the linearisation's step
    (`_linearisation`), the search (`_search`) is what a subclass supplies."""

    # (`stol` too, where it is not 0: 0 switches the statistical test off, a branch of
    # the compiled solve, `traced_options`)
    TRACED_OPTIONS = ("rtol", "atol", "gtol", "stol")
    TRACED_INTEGERS = ("max_steps",)

    rtol: eqx.AbstractVar[float]
    atol: eqx.AbstractVar[float]
    gtol: eqx.AbstractVar[float]
    stol: eqx.AbstractVar[float]
    max_steps: eqx.AbstractVar[int]
    strategy: eqx.AbstractVar[str]
    linear_solver: eqx.AbstractVar[str]
    cg_rtol: eqx.AbstractVar[float]
    cg_max_steps: eqx.AbstractVar[int]

    def traced_options(self, dtype):
        """As `AbstractSolver.traced_options`, with `stol = 0` kept a Python number: it
        switches the statistical test off (`_statistical`), which the compiled solve
        then leaves out; any other stol is a threshold like gtol."""
        out = super().traced_options(dtype)
        if _statistical_off(self.stol):
            return eqx.tree_at(lambda s: s.stol, out, self.stol)
        return out

    def _check(self):
        name = type(self).__name__
        if is_real(self.rtol) and not 0 <= self.rtol < 1:  # (a step test that always fires)
            raise ValueError(
                f"`{name}(rtol=...)` must be a number in [0, 1), got {self.rtol!r} (the first "
                f"positional argument is rtol: write `{name}(max_steps=...)` by keyword)."
            )
        check_options(
            self,
            non_negative=("rtol", "atol", "stol", "cg_rtol"),
            fractions=("gtol",),
            integers=("max_steps", "cg_max_steps"),
        )
        if self.cg_max_steps < 1:  # (no conjugate-gradient step: theta would never move)
            raise ValueError(
                f"`{name}(cg_max_steps=...)` must be an integer >= 1, got {self.cg_max_steps!r}."
            )
        as_strategy(self.strategy, f"`{name}(strategy=...)`")
        if self.linear_solver not in LINEAR_SOLVERS:
            raise ValueError(
                f"`{name}(linear_solver=...)` must be one of {LINEAR_SOLVERS}, "
                f"got {self.linear_solver!r}."
            )
        if isinstance(as_strategy(self.strategy), ParallelInTime) and self.linear_solver == "cg":
            raise ValueError(
                f"`{name}(linear_solver='cg')` runs its Jacobian-vector "
                "products by sequential recursions and does not combine with "
                "strategy='parallel': take linear_solver='dense' (or 'auto') there."
            )

    def _matrix_free(self, problem, params):
        # The parallel-in-time path forms the Jacobian (its sensitivities are associative
        # scans); the matrix-free products are sequential.
        if isinstance(as_strategy(self.strategy), ParallelInTime):
            return False
        p = params.theta.shape[0]
        fits = dense_jacobian_fits(problem, p + params.x0.shape[-1])
        return least_squares_solver(self.linear_solver, p, fits) == "cg"

    @abc.abstractmethod
    def _search(self) -> AbstractSearch:
        """The globalisation of the step."""

    def _linearise(self, problem, params, placeholder_only=False):
        """The linearisation at params (`_linearisation.linearise`) and h_min; with
        `placeholder_only`, zeros of their structure (`_linearisation.placeholder`)."""
        make = placeholder if placeholder_only else linearise
        return make(
            problem,
            params,
            self.strategy,
            self._matrix_free(problem, params),
            self.cg_rtol,
            self.cg_max_steps,
        )

    def _solve(self, problem, params, b, mu, active, active_x=None):
        """The damped Gauss-Newton step (the descent): the linearisation's `step`, the
        theta entries `active` and the x0 entries `active_x` (or None) held."""
        if active_x is not None:
            b = b.holding_x0(active_x)
        return b.step(problem, params, mu, active)

    def _active(self, problem, p_theta, g_t):
        if problem.lower is None:
            return jnp.zeros(p_theta.shape, bool)
        return _pushed_out(p_theta, g_t, problem.lower, problem.upper)

    def _active_x(self, problem, p_x0, g_x):
        """The x0 entries at a bound of their box that the gradient pushes outwards, or
        None without x0 bounds."""
        if not problem.x0_bounded:
            return None
        return _pushed_out(p_x0, g_x, problem.x0_lower, problem.x0_upper)

    primes_in_step = True

    def init(self, problem, params):
        # A placeholder linearisation (zeros of its shapes): the first `step` forms it
        # at `params` (`primes_in_step`), so that the compiled loop holds one copy.
        blocks, h_min = self._linearise(problem, params, placeholder_only=True)
        dtype = problem.dtype
        nan = jnp.array(jnp.nan, dtype)
        false = jnp.array(False)
        return LSQState(
            blocks,
            jnp.array(jnp.inf, dtype),
            h_min,
            self._search().init(dtype),
            data_scale(problem),
            Measures(nan, nan, nan, nan, false, false, jnp.zeros(params.theta.shape, bool), nan),
            jnp.array(False),
            RESULTS.converged,
            jnp.array(False),
            Params(*blocks.diagonals(params)),
        )

    def trial(self, problem, params, step, alpha):
        """The projected point params + alpha step (`_point`) and its loss (inf where not
        finite)."""
        new = self._point(problem, params, step, alpha)
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
        loss, whether it decreased C; a decrease at round-off is judged again by `_move`)."""
        C = b.C
        inv_t = 1.0 / floor(b.diag_t())
        if problem.project is not None:
            inv_t = jnp.full_like(inv_t, jnp.min(inv_t))
        inv_x = 1.0 / jax.vmap(lambda c: floor(jnp.diag(c)))(b.Cb) if params.x0.size else b.g_x
        dt, dx = -inv_t * b.g_t, -inv_x * b.g_x
        slope = -(b.g_t @ dt + jnp.sum(b.g_x * dx))
        curv = b.curvature(problem, params, dt, dx)
        t0 = jnp.where(curv > 0, slope / jnp.where(curv > 0, curv, 1.0), 1.0)
        t0 = jnp.where(jnp.isfinite(t0) & (t0 > 0), t0, 1.0)

        def point(t):
            new = Params(
                problem.feasible(params.theta + t * dt), problem.feasible_x0(params.x0 + t * dx)
            )
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

    def _point(self, problem, params, step, alpha):
        """The projected point params + alpha step."""
        return Params(
            problem.feasible(params.theta + alpha * step.theta),
            problem.feasible_x0(params.x0 + alpha * step.x0),
        )

    def _descent(self, problem, params, state):
        """The descent step from `params` (linearisation `state.blocks`) and its projected
        full point. Entries that the projection leaves where they are although the step
        moves them (at a bound, pushed outwards by the coupling with the other entries, or
        held by a general projection) are held too and the step solved again, so that the
        other entries take the step of the reduced problem. Under a box alone (sets
        combined with a general projection have no bounds of their own here,
        `problem.lower` None), so are entries the clip stops short of their step (a
        bound met on the way): they move there, and the others take the step that
        minimises the damped linear model with that move made (the gradient shifted by
        J^T J_t d, `shifted`), not the step that assumed them past it (which the clip made
        a poor point: a tank's outflow coefficient and level stepped for an inflow gain
        the bound refused, then 680 steps near the level's singularity at 0 where 14
        sufficed). The linear model can be poor far from a solution, so where the
        re-solved point has a higher loss than the plain projected one, the plain one is
        taken (two simulations, only where a step met a bound): the re-solved step of two
        nearly collinear gains, backtracked to nothing, had made Gauss-Newton creep where
        the plain one took it to the optimum. A re-solved point that is not finite (the
        step beyond the model's domain) stays, for the search to damp or shorten."""
        b = state.blocks
        mu = self._search().damping(state.search)
        act = self._active(problem, params.theta, b.g_t)
        act_x = self._active_x(problem, params.x0, b.g_x)
        h = self._solve(problem, params, b, mu, act, act_x)
        point = self._point(problem, params, h, 1.0)
        if act_x is not None:
            # x0 entries the box leaves where they are although the step moves them (at
            # a bound, pushed outwards by the coupling with the other entries): held, and
            # the step solved again
            blocked_x = (point.x0 == params.x0) & (h.x0 != 0) & ~act_x

            def again_x():
                h2 = self._solve(problem, params, b, mu, act, act_x | blocked_x)
                return h2, self._point(problem, params, h2, 1.0), act_x | blocked_x

            h, point, act_x = lazy_cond(jnp.any(blocked_x), again_x, (h, point, act_x))
        if problem.lower is not None:  # a box: the projection's moves
            clipped = (point.theta != params.theta + h.theta) & ~act & jnp.isfinite(h.theta)
            d = jnp.where(clipped, point.theta - params.theta, 0.0)

            def again():
                reduced = b.shifted(problem, params, d)
                h2 = self._solve(problem, params, reduced, mu, act | clipped, act_x)
                h2 = Params(jnp.where(clipped, d, h2.theta), h2.x0)
                point2 = self._point(problem, params, h2, 1.0)
                # (the lower of the two; a re-solved point that is not finite, the step
                # out of the model's domain, is left to the search to damp or shorten)
                C2 = self._loss(problem, point2)
                better = ~jnp.isfinite(C2) | (C2 <= self._loss(problem, point))
                pick = lambda a, c: jnp.where(better, a, c)  # noqa: E731
                return jax.tree_util.tree_map(pick, (h2, point2), (h, point))

            h, point = lazy_cond(jnp.any(clipped), again, (h, point))
        elif problem.constrained:
            blocked = (point.theta == params.theta) & (h.theta != 0) & ~act

            def again():
                h2 = self._solve(problem, params, b, mu, act | blocked, act_x)
                return h2, self._point(problem, params, h2, 1.0)

            h, point = lazy_cond(jnp.any(blocked), again, (h, point))
        return h, point

    def _move(self, problem, params, state, h, full, full_simulated, full_met) -> _Move:
        """The search along the descent step `h` (`full`: its projected full point and
        that point's loss, simulated where `full_simulated`, else its linearisation's, and
        `full_met`, whether that linearisation meets the first-order test) and the
        projected-gradient fallback: where the step ends, before the linearisation there.

        The search compares each trial's loss with the linearisation's C at the current
        point. A trial's simulated loss (`_loss`) is a second evaluation of C by another
        program, and the two differ by round-off, which in float32 with outputs far above
        the residuals reached 4e-5 C: Gauss-Newton then cycled between two points for 100
        steps, each step a "decrease" by one of the two programs. So where the search or
        the projected-gradient step finds a decrease within `SAME_PATH` times the
        round-off that the outputs' precision allows, the current point is also
        simulated: the difference of its two losses is the round-off of C there, and the
        decrease counts only above it, measured by one program (the trial's: the
        simulation, or the linearisation for a full step that linearises at its trial
        point). A decrease at round-off alone, of the step and of the gradient step, is a
        stall at round-off (`_Move.same_path_reject`). (A decrease above the round-off
        of C by either program is one by both: no other step simulates the point twice.)"""
        b = state.blocks
        search = self._search()
        # The decrease of C the linear model predicts for the full projected step:
        # -(2 s^T J^T r + ||J s||^2).
        st, sx = full[0].theta - params.theta, full[0].x0 - params.x0
        Js2 = b.curvature(problem, params, st, sx)
        pred = -(2.0 * (st @ b.g_t + jnp.sum(sx * b.g_x)) + Js2)
        t, search_state = search.search(
            lambda alpha: self.trial(problem, params, h, alpha), b.C, h, full, pred, state.search
        )
        eps = jnp.finfo(problem.dtype).eps
        resolved = SAME_PATH * eps * (jnp.sqrt(b.C * output_norm(problem)) + b.C)

        def simulated_here():
            return self._loss(problem, params)

        def same_program(near, C_sim, loss, simulated):
            # (a decrease above the round-off of C at this point, |C_sim - b.C|, measured
            # by the program that gave `loss`; the point simulated where `near`, once)
            C_sim = lazy_cond(near & jnp.isnan(C_sim), simulated_here, C_sim)
            same = jnp.where(simulated, C_sim, b.C)
            return ~near | (loss < same - jnp.abs(C_sim - b.C)), C_sim

        nan = jnp.array(jnp.nan, b.C.dtype)
        simulated = jnp.array(True) if full_simulated else ~t.at_full
        # (not where the full step's point meets the first-order test, `full_met`: the fit
        # ends there, and a decrease to it, at round-off or not, cannot start a cycle)
        near = t.accept & ~(t.at_full & full_met) & (b.C - t.loss <= resolved)
        ok, C_sim = same_program(near, nan, t.loss, simulated)
        accept = t.accept & ok
        # A step that failed: a projected-gradient step instead, which decreases C unless
        # theta is stationary. With a bound, a step that the projection clipped can
        # predict no decrease at any damping; on a rank-deficient Jacobian (a hybrid's
        # network) a larger damping alone creeps where this step makes progress
        # (`tests/test_hybrid_workflow.py`).
        need = ~accept
        arc = lazy_cond(
            need, lambda: self._gradient_arc(problem, params, b), (params, b.C, jnp.array(False))
        )
        arc_near = arc[2] & (b.C - arc[1] <= resolved)
        arc_ok, _ = same_program(arc_near, C_sim, arc[1], jnp.array(True))
        arc = (arc[0], arc[1], arc[2] & arc_ok)
        same_path_reject = (t.accept & ~ok) | (arc_near & ~arc_ok)
        take = accept | arc[2]
        new = jax.tree_util.tree_map(lambda a, c: jnp.where(accept, a, c), t.params, arc[0])
        new_loss = jnp.where(accept, t.loss, arc[1])
        params = jax.tree_util.tree_map(lambda a, c: jnp.where(take, a, c), new, params)
        loss = jnp.where(take, new_loss, state.loss)
        return _Move(
            params,
            loss,
            take,
            h,
            pred,
            t.gave_up & ~take,
            search_state,
            t.at_full & accept,
            same_path_reject & ~take,
        )

    def _linearises_trials(self, problem, params) -> bool:
        """Whether a step linearises at its trial point (its loss is the linearisation's
        C, and an accepted full step keeps that linearisation), rather than simulating the
        trial for its loss and linearising where the step ends: where the Jacobian is
        formed with at most `TRIAL_COLUMNS` columns per trajectory, the sensitivities cost
        about what the simulation costs, and this saves one simulation per step."""
        columns = params.theta.shape[0] + params.x0.shape[-1]
        return not self._matrix_free(problem, params) and columns <= TRIAL_COLUMNS

    def step(self, problem, params, state):
        """One iteration: the descent and its search (`_move`), the linearisation where the
        iterate moved and the stopping tests there. The first step (`state.primed` False)
        only forms the linearisation at the starting point and tests it (the first-order
        test and a negative penalty)."""
        b = state.blocks
        primed = state.primed
        zeros = Params(jnp.zeros_like(params.theta), jnp.zeros_like(params.x0))
        false = jnp.array(False)
        # The first step's move: none (its linearisation is at the start).
        nil = jnp.zeros((), problem.dtype)
        prime = _Move(params, state.loss, ~false, zeros, nil, false, state.search, ~false, false)
        if self._linearises_trials(problem, params):
            h, point = lazy_cond(
                primed, lambda: self._descent(problem, params, state), (zeros, params)
            )

            # One linearisation traced: at the trial point (the start, when priming), then
            # where the step ended if that is elsewhere (a shortened step, the gradient
            # arc): a loop of one or two passes.
            def linearise_and_search(c):
                phase, at, _, mv = c
                lin = self._linearise(problem, at)
                C = lin[0].C
                full = (at, jnp.where(jnp.isfinite(C), C, jnp.inf))
                # (where the full step's point meets the first-order test, the fit ends
                # there: its decrease needs no check at round-off, `_move`)
                met = lin[0].first_order(problem, at) <= self.gtol

                def search():
                    return lazy_cond(
                        primed,
                        lambda: self._move(problem, params, state, h, full, False, met),
                        prime._replace(loss=C),
                    )

                mv = lazy_cond(phase == 0, search, mv)
                again = (phase == 0) & mv.take & ~mv.at_full
                return jnp.where(again, 1, 2), mv.params, lin, mv

            _, _, lin, mv = jax.lax.while_loop(
                lambda c: c[0] < 2,
                linearise_and_search,
                (jnp.array(0), point, (b, state.h_min), prime),
            )
            blocks, h_min = jax.tree_util.tree_map(
                lambda a, c: jnp.where(mv.take, a, c), lin, (b, state.h_min)
            )
        else:

            def descend_and_move():
                h, point = self._descent(problem, params, state)
                full = (point, self._loss(problem, point))
                return self._move(problem, params, state, h, full, True, jnp.array(False))

            mv = lazy_cond(primed, descend_and_move, prime)
            blocks, h_min = lazy_cond(
                mv.take, lambda: self._linearise(problem, mv.params), (b, state.h_min)
            )
        return self._conclude(problem, params, state, mv, blocks, h_min)

    def _conclude(self, problem, old, state, mv, blocks, h_min):
        """The stopping tests at the new iterate `mv.params` (linearisation `blocks`), and
        the next state."""
        b = state.blocks
        dtype = problem.dtype
        eps = jnp.finfo(dtype).eps
        primed = state.primed
        false = jnp.array(False)
        params, take, h, pred = mv.params, mv.take, mv.h, mv.pred
        loss = jnp.where(primed, mv.loss, blocks.C)
        fo = blocks.first_order(problem, params)

        s = Params(params.theta - old.theta, params.x0 - old.x0)
        size_d = b.scaled_norm(old)
        step_d = b.scaled_norm(s)
        small_step = primed & take & (step_d <= self.rtol * size_d + self.atol)
        small_step = small_step & (state.loss - loss <= self.rtol * state.loss + self.atol)
        # Nothing left to gain at this precision: nothing decreased C (nor the
        # projected-gradient step after a failed one) and the predicted decrease is at
        # round-off (MINPACK's ftol test at machine epsilon), or the step is at the
        # round-off level of the parameters (matters in float32).
        size = jnp.sqrt(jnp.sum(old.theta**2) + jnp.sum(old.x0**2))
        hsize = jnp.sqrt(jnp.sum(h.theta**2) + jnp.sum(h.x0**2))
        round_off = ~take & (
            (pred <= 8 * eps * state.loss)
            | (hsize <= 10 * jnp.sqrt(eps) * jnp.maximum(size, jnp.finfo(dtype).tiny))
            | mv.same_path_reject
        )
        # At a zero residual the loss keeps falling by round-off (1e-36 and below) with
        # accepted steps of 1e-21: a step below round-off of the scaled parameters ends the
        # fit there. (Only there: on an ill-conditioned J, ||D p|| can be far above the
        # outputs, and such steps still move the fit.)
        zero = zero_residual(loss, state.scale)
        tiny = primed & take & (step_d <= eps * size_d)
        round_off = round_off | (tiny & zero)
        gave_up = mv.gave_up
        stalled = small_step | round_off | gave_up
        # Where the fit stops for lack of progress (round-off, the step test fired, or the
        # damping and the projected-gradient step both gave up), a measure below its
        # round-off limit is stationary to the precision of the loss (`_optimality`): the
        # decrease left, about fo^2 C, is at round-off.
        # (the columns that vanished along the fit measured at their largest norm: a
        # degenerate minimum, `_optimality.stall_test`)
        # (`state.top` holds the linearisations before this one, the start's included)
        d_t, d_x = blocks.diagonals(params)
        top = jax.tree_util.tree_map(jnp.maximum, state.top, Params(d_t, d_x))
        at_stall, still, degenerate = blocks.stall_test(problem, params, top.theta, top.x0, fo)
        met = fo <= self.gtol
        degenerate = stalled & ~met & degenerate
        stationary = met | (stalled & still)
        se, statistical = self._statistical(problem, old, s, b, state.loss, loss, primed & take, fo)
        negative = h_min < 0
        # Where no step decreases C at its round-off (an output offset far above the noise
        # leaves the loss too few digits to confirm the last ones), a regular Jacobian's
        # undamped step within stol standard errors settles the point (`_settled`).
        stuck = (round_off | gave_up) & ~stationary & ~statistical & ~zero & ~negative
        se_at, settled = self._settled(problem, params, blocks, fo, stuck)
        se = jnp.where(settled, se_at, se)
        statistical = statistical | settled
        fo = jnp.where(degenerate, at_stall, fo)  # (the measure the stop was tested on)
        done = stationary | statistical | stalled | negative
        result = RESULTS.where(
            stationary,
            RESULTS.converged,
            RESULTS.where(
                statistical,
                RESULTS.statistically_converged,
                RESULTS.where(
                    zero,
                    RESULTS.zero_residual,
                    RESULTS.where(gave_up, RESULTS.no_progress, RESULTS.stalled),
                ),
            ),
        )
        result = RESULTS.where(negative, RESULTS.negative_penalty, result)
        tiny = jnp.finfo(dtype).tiny
        nan = jnp.array(jnp.nan, dtype)
        measures = Measures(
            fo,
            jnp.where(primed, step_d / jnp.maximum(size_d, tiny), nan),
            jnp.where(
                primed,
                jnp.where(take, pred, jnp.maximum(pred, 0.0)) / jnp.maximum(state.loss, tiny),
                nan,
            ),
            se,
            small_step,
            degenerate,
            vanished_columns(d_t, top.theta, d_x, top.x0)[0],
            stall_limit(problem, blocks.C),
        )
        state = LSQState(
            blocks, loss, h_min, mv.search, state.scale, measures, done, result, ~false, top
        )
        return params, state

    def _statistical(self, problem, old, s, b, C_old, C, take, fo):
        """The statistical convergence test (`_optimality.standard_errors`) of the step
        `s` taken from `old` (linearisation `b`, loss `C_old`) to a point of loss `C`
        and first-order measure `fo`: the step's size in standard errors, and whether theta's
        columns of J (the x0 columns eliminated) are rank deficient, the step, its
        predicted decrease confirmed by the actual one (at least a quarter of it), is at
        most `stol` standard errors, no parameter alone would move by a standard
        error (fo sqrt(R - rank) <= 1: the cosine times sqrt(R - rank) is a
        one-parameter Gauss-Newton step in its own standard error), and the undamped
        step is at most sqrt(rank) standard errors.
        The rank (an eigendecomposition) is formed only where the rest of the test holds.
        Off (NaN, False) with `stol=0` and where J^T J is not formed
        (`linear_solver="cg"`)."""
        dtype = problem.dtype
        if _statistical_off(self.stol) or not b.forms_normal_matrix:
            return jnp.array(jnp.nan, dtype), jnp.array(False)
        pred = -(
            2.0 * (s.theta @ b.g_t + jnp.sum(s.x0 * b.g_x))
            + b.curvature(problem, old, s.theta, s.x0)
        )
        actual = C_old - C
        n_obs = n_observations(problem)
        n_free = s.theta.size + s.x0.size
        # With the full rank n_free (the fewest degrees of freedom) both sizes are
        # smallest: the rank is formed only where they pass.
        dof_min = jnp.maximum(n_obs - n_free, 0)
        tiny = jnp.finfo(dtype).tiny
        se_min = jnp.sqrt(jnp.maximum(pred, 0.0) * dof_min / jnp.maximum(C, tiny))
        # (pred > 0: where the linear model predicts no decrease, at round-off, the step
        # measures nothing; an unstable start, whose columns were parallel to 1e-14, took
        # such a step at a loss 1e4 times the optimum's and read 0 standard errors)
        candidate = take & (pred > 0) & (actual > 0) & (actual >= 0.25 * pred)
        candidate = candidate & (se_min <= self.stol) & (fo * jnp.sqrt(dof_min) <= 1.0)
        p = s.theta.size
        rank, rank_t, pred_full = lazy_cond(
            candidate,
            lambda: self._undamped(problem, old, b),
            (jnp.asarray(n_free, jnp.int32), jnp.asarray(p, jnp.int32), jnp.zeros((), dtype)),
        )
        se = standard_errors(pred, C, n_obs, rank)
        within = (se <= self.stol) & (fo * jnp.sqrt(n_obs - rank) <= 1.0)
        # The undamped step's own size, at most sqrt(rank J) standard errors: the point the
        # linear model leads to is within the confidence region of this one (pred_full at
        # most rank J sigma^2, the mean of its chi^2). A far damped oscillator whose steps
        # backtracked 2^-20 had taken 1e-4 standard errors where the full step, 3 standard
        # errors, predicted 9 sigma^2 at rank 3: a loss 170 times the optimum's.
        se_full = standard_errors(pred_full, C, n_obs, rank)
        within = within & (se_full**2 <= rank)
        # Over-parameterised theta only: a null space of the initial states alone (an
        # unobservable state, or x0 columns nearly parallel at a poor point) does not
        # make the steps creep, and the first-order test decides there.
        return se, candidate & (rank_t < p) & within

    def _undamped(self, problem, at, b):
        """(rank J, rank S, pred): the numerical ranks (`AbstractLinearisation.rank`) and
        the decrease of C that the undamped step from `at` (linearisation `b`) predicts:
        the pseudo-inverse's Gauss-Newton step, without the backtracking or the damping
        of the steps taken. Without bounds from the rank's eigendecomposition of S (no
        second solve to compile), with them the step of the active set."""
        if problem.lower is None and not problem.x0_bounded:
            rank, rank_t, full = b.rank_and_decrease()
            return rank.astype(jnp.int32), rank_t.astype(jnp.int32), full
        act = self._active(problem, at.theta, b.g_t)
        act_x = self._active_x(problem, at.x0, b.g_x)
        h = self._solve(problem, at, b, jnp.zeros((), problem.dtype), act, act_x)
        full = -(
            2.0 * (h.theta @ b.g_t + jnp.sum(h.x0 * b.g_x))
            + b.curvature(problem, at, h.theta, h.x0)
        )
        return tuple(r.astype(jnp.int32) for r in b.rank()) + (full,)

    def _settled(self, problem, params, b, fo, stopped):
        """The statistical test of a point where no step decreases C at its round-off
        (`stopped`: a stall or a failed search at `params`, linearisation `b`, measure
        `fo`) on a regular Jacobian: the undamped Gauss-Newton step from there, a
        prediction the loss can no longer confirm, is its size in standard errors
        (`_optimality.standard_errors`). Returns that size (NaN where not tested) and
        whether the point is settled: theta's columns of J (the x0 columns eliminated)
        have full rank, the step is at most `stol` standard errors and no parameter
        alone would move by one (fo sqrt(R - rank J) <= 1). The rank and the step (an
        eigendecomposition, or a solve under bounds) are formed only where the fit
        stopped so. Off (NaN, False) with `stol=0` and where J^T J is not formed
        (`linear_solver="cg"`). (Where the residuals' curvature cancels most of J^T J,
        the Gauss-Newton step is short of the distance left: `fit` checks a settled
        stop with the Newton step after the solve, `_optimality.newton_distance`.)"""
        dtype = problem.dtype
        off = (jnp.array(jnp.nan, dtype), jnp.array(False))
        if _statistical_off(self.stol) or not b.forms_normal_matrix:
            return off
        n_obs = n_observations(problem)
        p = params.theta.size

        def test():
            rank, rank_t, pred = self._undamped(problem, params, b)
            se = standard_errors(pred, b.C, n_obs, rank)
            ok = (rank_t == p) & (se <= self.stol) & (fo * jnp.sqrt(n_obs - rank) <= 1.0)
            return se, ok

        return lazy_cond(stopped, test, off)

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
        blocks = None if problem.cost.penalty is not None else b.covariance_blocks(state.loss)
        return params, loss, blocks
