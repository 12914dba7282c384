"""First-order optimality: the measure on which every solver of `fit` declares success.

A fit succeeds only at a (constrained) stationary point of C (eq. 5/21), tested in
variables that do not depend on the parameters' units. With g = J^T r (half the gradient
of C = ||r||^2, eq. 17/20) and d_i = ||J e_i|| the norm of the residual Jacobian's
column i (Marquardt's scaling), the unconstrained measure is MINPACK's gradient test,

    max_i |g_i| / (d_i ||r||),

the largest cosine between the residual and a column of the Jacobian (More, Garbow and
Hillstrom, "User guide for MINPACK-1", 1980, the `gtol` test): 0 at a stationary point,
at most 1, and invariant to the scaling of the parameters and of the loss.

With constraints it is the projected gradient in the same scaled variables: for a step
theta+ = P(theta - t grad C) with the diagonal-Newton step sizes t_i = 1 / (2 d_i^2)
(P a box, which commutes with a diagonal metric, or the prox of a separable
regulariser), the measure is max_i |theta+_i - theta_i| d_i / ||r||, which is the cosine
where the bound is inactive and 0 where theta sits at a bound that the gradient pushes
against (Conn, Gould and Toint, "Global convergence of a class of trust region
algorithms for optimization with simple bounds", 1988; Kanzow, Yamashita and Fukushima,
"Levenberg-Marquardt methods with strong local convergence properties for solving
nonlinear equations with convex constraints", 2004). A general convex projection is
applied with one step size t = min_i t_i (the Euclidean projection does not commute
with a diagonal metric; a common t keeps its fixed points the stationary points).
Round-off of theta - t grad C (4 eps |theta_i|) is not counted.

A loss evaluated in floating point resolves the measure down to about sqrt(eps) only
(`roundoff_limit`): where no step decreases C any more, a measure below 10 sqrt(eps)
also counts as stationary. The residuals r = z - z_hat are themselves known only to the
precision of the outputs, eps ||z_hat|| at best (the rounding of z_hat alone): where the
outputs are far above the residuals (float32 outputs of scale 30 with noise 1e-3), that
error moves every cosine by up to eps ||z|| / ||r|| (3.6e-3 there), and a stall at the
optimum measured 4.6e-3, above 10 sqrt(eps) = 3.5e-3. So a stall is tested at
`stall_limit`, 10 max(sqrt(eps), eps ||z|| / ||r||) (at most `STALL_LIMIT_MAX`), which
is 10 sqrt(eps) in float64 unless ||r|| is below 1.5e-8 ||z||.

At a degenerate minimum a column of J vanishes with the gradient (a parameter c entering
as c^2 u, the minimum at c = 0: J e_c = 2 c u and g_c = 2 c u^T r), and its cosine stays
at |u^T r| / (||u|| ||r||), however close to the minimum: the measure is then no test of
stationarity. Where no step decreases C any more (a stall), a column whose squared norm
has shrunk 1e8 times more than the least-shrunk column (its squared norm against the
largest it had along the fit) is measured at that largest norm instead (More's running
scaling, "The Levenberg-Marquardt algorithm: implementation and theory", 1978, eq.
(6.3); `stall_test`): the gradient is then tested in the scaling the parameter had
before its column vanished, and the fit converges there where that measure is below the
round-off limit and no step along those columns lowers C by more than sqrt(eps) C
(`descends`, checked once after the solve by `refuted`; `Measures.degenerate` says
so). Relative shrinkage, because every column
shrinks alike where the start was unstable (1e20 there), a change of the loss's scale;
the descent, because a float32 fit whose columns of R and C shrank 1e8-fold in one step
read stationary at their largest norm with a loss 7000 times the optimum's. Whatever
the stop, `Measures.vanished` names the columns that vanished along the fit: a term that
switched itself off (a gain at 0, a closed gate), at a minimum or on a plateau.

Where the data determine the outputs exactly (a zero-residual fit, noise-free data), r
is round-off at the solution and the cosine is meaningless; `zero_residual` tests the
loss against the round-off level of the data instead, and `refuted` checks after the
solve that no step along every column still lowers it (a loss below that level can
still be 20 times the optimum's on noisy float32 data).

Over-parameterised models (a network in theta) have a Jacobian with a null space and,
next to it, directions the data determine only weakly, along which the linear model of
the residuals holds over tiny distances only. The least-squares solvers then creep: each
step is accepted, the loss keeps decreasing by statistically meaningless amounts, and
the cosine stays far above gtol (a pendulum whose damping is an MLP of the rate, 29 free
variables of rank 15 at 400 samples: measure 2.3e-3 after 3000 Levenberg-Marquardt
steps; `benchmarks/hybrid_stopping.py`). The Gauss-Newton step of the pseudo-inverse does
not settle it: it still predicts a decrease of 3.3 sigma^2 there (1.8 standard errors),
along directions where a thousandth of it raises the loss by 1e4 sigma^2. Where theta's
columns of the Jacobian are rank deficient once the x0 columns are eliminated (the Schur
complement S of `_linalg.schur_complement`), the least-squares solvers therefore also stop
at *statistical convergence*
(`RESULTS.statistically_converged`, `standard_errors`): with sigma^2 = C / (R - rank J)
the residual variance (R the number of observations), a step s whose predicted decrease
pred = -(2 s^T J^T r + ||J s||^2) >= ||J s||^2 is at most stol^2 sigma^2 moves every
quantity the data determine, any c^T theta with c in the row space of J, by at most

    |c^T s| <= ||J s|| sqrt(c^T (J^T J)^+ c) <= stol SE(c^T theta)

(Cauchy-Schwarz in the metric J^T J). The test is that of MINPACK's ftol and
scipy's `least_squares` (the predicted and the actual relative decrease, on a step where
the model agrees with the loss: actual >= pred / 4) with the tolerance stol^2 / (R -
rank J) set by the noise instead of machine precision. A step can be small because the
damping is large (after rejected steps) rather than because nothing is left; so the
test also asks that no parameter alone would move by a standard error: the cosine
times sqrt(R - rank J) is the Gauss-Newton step of one parameter in its own standard
error, and is at most 1; and that the undamped Gauss-Newton step (the pseudo-inverse's)
predicts at most rank J sigma^2, the mean of its chi^2 (the point the linear model leads
to is within the confidence region of this one: a damped rotation far from its optimum,
whose steps backtracked 2^-20, moved 1e-4 standard errors where the undamped step
predicted 9 sigma^2 at rank 3); and a step whose linear model predicts no decrease
measures nothing. It is scale invariant (ratios of losses and a count) and is
tested only where S is rank deficient: on a regular Jacobian Gauss-Newton converges
quadratically and the first-order test decides as before, and a null space of the
initial states alone (an unobservable state, or x0 columns nearly parallel at a poor
point: a partly observed Duffing oscillator far from its optimum had x0 columns 3.5e-7
from parallel) does not make the fit creep either. It bounds one step, not the
creep of many: where the creep drifts coherently, a loose stol stops early (on the
pendulum above, stol = 0.03 stopped at step 59 with w0sq 0.89 standard errors from
where 3000 steps take it; the default 0.01 stopped at step 2494, 0.01 standard errors
from it).

On a regular Jacobian the same measure settles a stall. Where the outputs carry an offset
far above the noise, the loss has fewer digits than the last steps need (an offset of 1e4
around a noise of 1e-3: the residuals' round-off, eps 1e4, is 2e-9 of them): no step
decreases C at its round-off while the measure is still above its round-off limit
(Levenberg-Marquardt stopped at 7.5e-7, 5e-5 standard errors from the optimum). There the
undamped Gauss-Newton step predicts what the loss can no longer confirm, and a point from
which it is at most stol standard errors (pred <= stol^2 sigma^2), with no parameter alone
moving by one, is `statistically_converged` too (`AbstractLeastSquares._settled`); the
point the linear model leads to is then within stol standard errors of this one. Where
the residuals' curvature cancels most of J^T J (a large structured misfit), the
Gauss-Newton step is short of the distance left, so after the solve the Newton step with
the loss's own Hessian checks the stop (`newton_distance`); a first-order solver's stall
(L-BFGS's line search failing there) is settled by that step alone (`SETTLE_SE`).

In a precision below float64 the normal equations lose the weakly determined directions
first: `_linalg.scaled_eigh`'s cut (1e3 eps, 1.2e-4 of the largest scaled eigenvalue in
float32) calls a direction null whose singular value in J is 1e-2 of the largest, and
the steps do not move along it. Such a direction is no network's null space: the
undamped step's decrease that the statistical test bounds counts it with its eigenvalue
floored at the cut (`_linalg.eigh_solve(floored=True)`, a lower bound on what it would
give), in every precision, so that the test does not take it for a null space.
(Flooring it in the steps too, or only from a hundredth of the cut up, moved float32
hybrids along their networks' null directions, whose gradient is round-off: their
statistical stop no longer came.) After the solve, in such a precision, the
Gauss-Newton step computed from J itself (`gauss_newton_refutes`) checks a success
that the normal equations decided (`stalled` where that step moves the estimates by
more than a standard error and the loss confirms it), and a failure: where J^T J loses
a direction that J keeps, more steps will not help, and the message says to fit in
float64.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._cost import weigh
from ._linalg import NULL_CUT, floor, numerical_rank
from ._problem import FitProblem, Params
from ._strategy import dense_jacobian_fits

# A decrease of the objective counts where it is above this many eps of its round-off,
# sqrt(C Z) + C (Z the outputs' squared size, `output_norm`): two evaluations of one point
# by two programs (a simulation and a linearisation) differ by up to about that.
SAME_PATH = 100.0

# A column of J has vanished along the fit where its squared norm is at most this fraction
# of the largest it had (a norm below 1e-4 of it), in every precision (`stall_test`).
VANISHED = 1e-8

# The most the round-off limit of a stall may be raised to by the precision of the outputs
# (`stall_limit`): a cosine of 0.03 leaves about 1e-3 C to gain. Beyond it a stall is a
# failure, however imprecise the outputs.
STALL_LIMIT_MAX = 0.03

# The loss of a zero-residual fit, relative to `data_scale` (about the loss of predicting
# each output's mean), at which the residuals count as round-off: eps in float64 (a
# relative RMS residual of 1.5e-8) and in float32 (3.5e-4).
ZERO_RESIDUAL_RTOL = 1.0


@functools.cache
def roundoff_limit(dtype):
    """The first-order measure below which a point is stationary to the precision of its
    loss: 10 sqrt(eps) (1.5e-7 in float64, 3.5e-3 in float32). A loss C known to a
    relative precision eps cannot tell a point whose cosines are below about sqrt(eps)
    from the optimum (the decrease left, about cos^2 C, is at round-off), so a fit that
    converges linearly can stop there, above a tighter `gtol`."""
    return 10.0 * float(np.sqrt(np.finfo(dtype).eps))


def stall_limit(problem: FitProblem, C):
    """The first-order measure below which a stall (no step decreases C) is stationary to
    the precision of its loss and of its residuals: 10 max(sqrt(eps), eps sqrt(Z / C)),
    with Z = `output_norm` the loss of predicting zero outputs (see the module docstring),
    at least `roundoff_limit` and at most max(`STALL_LIMIT_MAX`, `roundoff_limit`)."""
    return stall_limit_of(problem.dtype, output_norm(problem), C)


def stall_limit_of(dtype, Z, C):
    """`stall_limit` from Z = `output_norm` (a solver that keeps it in its state)."""
    base = roundoff_limit(dtype)
    eps, tiny = jnp.finfo(dtype).eps, jnp.finfo(dtype).tiny
    ratio = jnp.sqrt(Z / jnp.maximum(jnp.abs(C), tiny))
    raised = jnp.minimum(10.0 * eps * ratio, max(STALL_LIMIT_MAX, base))
    return jnp.where(jnp.isfinite(raised), jnp.maximum(raised, base), base).astype(dtype)


def resolution(dtype):
    """The smallest first-order measure the arithmetic resolves: 0.5 sqrt(eps) (7.5e-9 in
    float64, 1.7e-4 in float32). At a measure below it the decrease left, about fo^2 C,
    is under eps C / 4, the round-off of the loss itself, so a positive `gtol` below it
    (the default 1e-8 is, in float32) is met there: a first-order solver, which has no
    stall to wait for, could not meet it otherwise."""
    return 0.5 * float(np.sqrt(np.finfo(dtype).eps))


def gtol_at_least_resolution(gtol, dtype):
    """A positive `gtol` counted as at least the `resolution` of `dtype` (0 stays 0): the
    tolerance of a first-order test that has no stall to wait for."""
    return jnp.where(gtol > 0, jnp.maximum(gtol, resolution(dtype)), gtol)


class Measures(NamedTuple):
    """The quantities a stop is tested on, at the returned point (NaN where a solver has no
    such test): the first-order measure, the last step's scaled size (relative to the
    scaled parameters), the decrease of the loss the last step's linear model predicted
    (relative to the loss), the last step's size in standard errors
    (`standard_errors`), whether the optional step test (rtol, atol) fired, whether the
    first-order measure is that of a stall with vanished Jacobian columns measured at
    their largest norm along the fit (`stall_test`), and which theta columns vanished
    along the fit (`vanished_columns`; a scalar False where a solver keeps no record)."""

    first_order: jax.Array
    step: jax.Array
    decrease: jax.Array
    standard_errors: jax.Array
    step_test: jax.Array
    degenerate: jax.Array
    vanished: jax.Array
    limit: jax.Array  # the round-off limit of a stall there (`stall_limit`; NaN: none)


def no_measures(dtype) -> Measures:
    nan = jnp.array(jnp.nan, dtype)
    false = jnp.array(False)
    return Measures(nan, nan, nan, nan, false, false, false, nan)


def _measured(problem: FitProblem):
    """The mask of the measured output samples, the shape of z (None without a mask)."""
    if problem.mask is None:
        return None
    out = problem.mask.outputs
    return jnp.broadcast_to(out if out.ndim == problem.z.ndim else out[..., None], problem.z.shape)


def n_observations(problem: FitProblem):
    """The number R of observations among the measured output samples
    (`Cost.observations`: an output of zero weight counts none, and a singular weight
    matrix counts its rank per sample)."""
    m = _measured(problem)
    if m is None and problem.cost.weight is None:
        return problem.z.size
    m = jnp.ones(problem.z.shape, bool) if m is None else m > 0
    return problem.cost.observations(m)


def standard_errors(pred, C, n_obs, rank):
    """The size of a least-squares step in standard errors (see the module docstring):
    sqrt(pred / sigma^2) with sigma^2 = C / (R - rank), an upper bound on the change of
    every quantity the data determine, in its own standard error (inf where R <= rank).

    **Arguments:**

    - `pred`: the decrease of the loss the step's linear model predicts,
        -(2 s^T J^T r + ||J s||^2) (at least ||J s||^2 for a Gauss-Newton or
        Levenberg-Marquardt step).
    - `C`: the loss C = ||r||^2 after the step (eq. 5/21).
    - `n_obs`: R, the number of observations (`n_observations`).
    - `rank`: the numerical rank of J (`_linalg.numerical_rank`, the cutoff of the
        covariance).

    **Returns:** a scalar >= 0.
    """
    dof = n_obs - rank
    tiny = jnp.finfo(jnp.result_type(C)).tiny
    se = jnp.sqrt(jnp.maximum(pred, 0.0) * dof / jnp.maximum(C, tiny))
    return jnp.where(dof > 0, se, jnp.inf)


def first_order(problem: FitProblem, params: Params, C, g: Params, d_t, d_x):
    """The first-order measure at `params` (see the module docstring).

    **Arguments:**

    - `problem`: the fit's `FitProblem` (its box bounds, projection and regulariser).
    - `params`: the free variables.
    - `C`: the smooth loss C = ||r||^2 at `params`.
    - `g`: half its gradient, J^T r, as `Params`.
    - `d_t`, `d_x`: diag(J^T J) of the theta columns (p,) and of each trajectory's x0
        columns (N, m).

    **Returns:**

    A non-negative scalar, 0 at a constrained stationary point: at most 1 (up to
    round-off) without a projection or with box bounds; a general projection, which
    may move coordinates the gradient does not, can give more.
    """
    dtype = problem.dtype
    eps = jnp.finfo(dtype).eps
    # (|C|: a first-order solver's C with a signed penalty may be negative; C >= 0 for
    # least squares)
    norm = jnp.sqrt(jnp.maximum(jnp.abs(C), jnp.finfo(dtype).tiny))
    # Marquardt's diagonal floored only at round-off of its largest entry (eps^2): the
    # damping's floor of 1e-12 divided the cosine of a parameter in small units (a column
    # norm 1e-15 of the largest) by up to 1e9, and a fit at its start read "converged".
    # (|g_i| <= sqrt(d_i) ||r||: the cosines stay <= 1 however small d_i.)
    rel = jnp.finfo(dtype).eps ** 2
    dt2 = floor(d_t, rel) if d_t.size else d_t
    dx2 = floor(d_x, rel) if d_x.size else d_x
    # x0's cosines, in its box where it has one (its projected gradient).
    # (a column that is exactly zero, every column of a model whose outputs do not
    # depend on the variables, has g_i = 0 and d_i = 0: its cosine is 0, not 0 / 0)
    c_x = _cosine(g.x0, dx2, norm) if g.x0.size else g.x0
    if g.x0.size and problem.x0_bounded:
        t = 0.5 / jnp.where(dx2 > 0, dx2, 1.0)
        step = params.x0 - t * 2.0 * g.x0
        trial = problem.feasible_x0(step)
        c_x = _projected_cosine(params.x0, g.x0, dx2, norm, t, step, trial, eps)
    theta = params.theta
    if not theta.size:
        return jnp.max(c_x, initial=0.0)
    constrained = problem.constrained or problem.regulariser is not None
    if not constrained:
        c_t = _cosine(g.theta, dt2, norm)
        return jnp.maximum(jnp.max(c_t), jnp.max(c_x, initial=0.0))
    t = 0.5 / jnp.where(dt2 > 0, dt2, 1.0)  # (dt2 = 0: every column zero, g = 0)
    if problem.project is not None:
        t = jnp.full_like(t, jnp.min(t))
    step = theta - t * 2.0 * g.theta
    trial, resolved = problem.prox_feasible(step, t)
    c_t = _projected_cosine(theta, g.theta, dt2, norm, t, step, trial, eps)
    if problem.project is not None:
        c_t = _along_the_set(theta, g.theta, dt2, norm, step, trial, eps, c_t)
    # (a prox of g and a set that its rounds did not resolve certifies nothing: inf)
    c_t = jnp.where(resolved, c_t, jnp.inf)
    return jnp.maximum(jnp.max(c_t), jnp.max(c_x, initial=0.0))


def _projected_cosine(x, g, d2, norm, t, step, trial, eps):
    """The scaled projected gradient of entries x: the move from x of their gradient step
    `step` = x - 2 t g after its projection (and prox) `trial`, in the units of the cosine
    (0 at a bound that the gradient pushes outwards). An entry that neither the prox nor
    the projection moved from the gradient step is an unconstrained one there: its
    cosine, |g_i| / (sqrt(d_i) ||r||), exactly. (A general projection's one common step
    t, that of the largest column, moves an entry of a column 1e7 times smaller by less
    than its round-off: the difference read 0, and a fit "converged" at its start, 0.998
    from stationary.)"""
    moved = jnp.maximum(jnp.abs(trial - x) - 4 * eps * jnp.abs(x), 0.0)
    c = jnp.where(moved == 0, 0.0, moved / (2.0 * t * jnp.sqrt(d2) * norm))
    return jnp.where(trial == step, _cosine(g, d2, norm), c)


def _along_the_set(x, g, d2, norm, step, trial, eps, c):
    """A general projection's measure of the entries it moved (`trial` != `step`): the
    smaller of each one's own (`c`, `_projected_cosine`) and the cosine of their move
    delta (beyond round-off) together, |g^T delta| / (sqrt(sum d_i delta_i^2) ||r||),
    the decrease along the set's surface in the Jacobi-scaled norm of that direction; `c`
    for the other entries. Each moved entry's own cosine divided a component along the
    surface by its own column norm: at the optimum on a + b <= C with b in small units
    (its column 0.019 of a's), the gradient left at round-off along the surface read
    2.3e-6, a stall, where the surface's direction (which moves a as much as b) reads
    1.9e-8. The decrease g^T delta counts beyond the round-off of the projected point
    only. (The joint cosine is that of delta's direction, whatever its size: a move left
    by an iterative projection's tolerance (Dykstra's, at a box's corner on a halfspace)
    read 1.6e-3 at the optimum, where each entry's own measure, which scales with the
    move, is 0: the smaller of the two is taken. Where the move has one entry, they are
    the same; where it mixes entries of different column norms, the joint one bounds the
    decrease of that direction.)"""
    touched = trial != step
    moved = jnp.maximum(jnp.abs(trial - x) - 4 * eps * jnp.abs(x), 0.0)
    delta = jnp.where(touched, jnp.sign(trial - x) * moved, 0.0)
    # (less the round-off of the projected point, 4 eps |x_i| per entry, times |g_i|: the
    # projection back onto the surface leaves a move across it of that size, which the
    # gradient normal to the surface, large at an active constraint, turns into a
    # decrease that is not there)
    roundoff = jnp.sum(jnp.where(touched, jnp.abs(g) * 4 * eps * jnp.abs(x), 0.0))
    num = jnp.maximum(jnp.abs(jnp.sum(g * delta)) - roundoff, 0.0)
    den = jnp.sqrt(jnp.sum(d2 * delta * delta)) * norm
    joint = jnp.where(num == 0, 0.0, num / jnp.where(den > 0, den, 1.0))
    return jnp.where(touched, jnp.minimum(joint, c), c)


def _cosine(g, d, norm):
    """|g_i| / (sqrt(d_i) ||r||), 0 where g_i = 0 (also where d_i = 0)."""
    return jnp.where(g == 0, 0.0, jnp.abs(g) / (jnp.sqrt(d) * norm))


def vanished_columns(d_t, top_t, d_x, top_x):
    """The theta and x0 columns that vanished along the fit, each a mask of its `d`'s
    shape: d_i / top_i <= VANISHED s with 0 < top_i < inf, s the largest d_j / top_j of
    all the columns. Relative to s: where every column shrank alike (a start at which the
    model was unstable, whose columns were 1e20 times those at the fit's end), the loss's
    scale changed, and no term switched itself off."""

    def ratio(d, top):
        # (Not where top is inf: a column that overflowed, inf <= VANISHED * inf, did not
        # vanish.)
        ok = (top > 0) & jnp.isfinite(top)
        return ok, jnp.where(ok, d / jnp.where(ok, top, 1.0), 0.0)

    (ok_t, r_t), (ok_x, r_x) = ratio(d_t, top_t), ratio(d_x, top_x)
    s = jnp.maximum(jnp.max(r_t, initial=0.0), jnp.max(r_x, initial=0.0))
    s = jnp.where(s > 0, s, 1.0)
    return ok_t & (r_t <= VANISHED * s), ok_x & (r_x <= VANISHED * s)


def stall_test(problem: FitProblem, params: Params, C, g: Params, d_t, d_x, top_t, top_x, fo=None):
    """The first-order test where no step decreases C any more (a stall; see the module
    docstring): the measure `first_order`, stationary at most `stall_limit`; and, where
    that fails, the measure with the columns that vanished along the fit at the largest
    norm they had (`vanished_columns`; More 1978, eq. (6.3)), stationary at most the
    same limit (a candidate that `refuted` checks after the solve).

    **Arguments:**

    - `problem`, `params`, `C`, `g`, `d_t`, `d_x`: as for `first_order`.
    - `top_t`, `top_x`: the largest diag(J^T J) of each column along the fit (the shapes
        of `d_t` and `d_x`).
    - `fo`: `first_order` at `params` where the caller has it (else computed here).

    **Returns:**

    The measure the stall is tested on, whether it is stationary (at most `stall_limit`),
    and whether that measure is the one with the vanished columns (a degenerate minimum).
    """
    limit = stall_limit(problem, C)
    if fo is None:
        fo = first_order(problem, params, C, g, d_t, d_x)
    gone_t, gone_x = vanished_columns(d_t, top_t, d_x, top_x)
    kept = first_order(
        problem, params, C, g, jnp.where(gone_t, top_t, d_t), jnp.where(gone_x, top_x, d_x)
    )
    degenerate = (fo > limit) & (kept <= limit)
    return jnp.where(degenerate, kept, fo), (fo <= limit) | degenerate, degenerate


# The step sizes `descends` tries, relative to the diagonal Gauss-Newton step.
DESCENT_TRIALS = tuple(10.0**-k for k in range(8))


def descends(problem: FitProblem, params: Params, g: Params, d: Params, along: Params, strategy):
    """Whether a step along the columns `along` (boolean `Params`: those that vanished
    along the fit, or every column) decreases the objective beyond its round-off: the
    diagonal Gauss-Newton step -g_i / d_i of those columns alone (theta's projected),
    scaled by each of `DESCENT_TRIALS`, against the objective at `params` evaluated by the
    same program: a decrease counts above sqrt(eps) C and above the round-off `SAME_PATH`
    eps (sqrt(C Z) + C), Z the outputs' `output_norm`. At a degenerate minimum (c^2 u,
    the minimum at c = 0) every such step along the vanished columns raises C or leaves it
    within that; on a plateau at a limit (a closed gate sigmoid(s) w, s -> -inf) the step
    gains what the term still contributes, 1e-10 C there; where one lowers C more, the
    vanished columns' measure is no test of stationarity. At a zero residual (round-off
    residuals, C about eps^2 Z) no step lowers C by the round-off bound, which is then
    above C itself."""
    dtype = problem.dtype
    eps = jnp.finfo(dtype).eps

    def objective(p):
        return problem.loss(p, strategy) + problem.g(p.theta)

    def diagonal_step(g, d, on):
        return jnp.where(on, -g / floor(d, eps**2), 0.0) if d.size else d

    here = objective(params)
    round_off = SAME_PATH * eps * (jnp.sqrt(jnp.abs(here) * output_norm(problem)) + jnp.abs(here))
    resolved = jnp.maximum(round_off, jnp.sqrt(eps) * jnp.abs(here))
    step = jax.tree_util.tree_map(diagonal_step, g, d, along)

    def lower(alpha):
        theta = params.theta + alpha * step.theta
        if params.theta.size and (problem.constrained or problem.regulariser is not None):
            theta = problem.feasible(theta)
        value = objective(Params(theta, problem.feasible_x0(params.x0 + alpha * step.x0)))
        return jnp.isfinite(value) & (value < here - resolved)

    alphas = jnp.asarray(DESCENT_TRIALS, dtype)
    return jnp.any(jax.lax.map(lower, alphas)) & jnp.isfinite(here)


def refuted(problem: FitProblem, params: Params, along: Params, strategy):
    """After a solve that reported a stop where no step lowers the loss, a degenerate
    minimum (`stall_test`) or a zero residual (`zero_residual`): whether a step along the
    columns `along` (boolean `Params`: theta's vanished columns, or every column) still
    lowers the objective (`descends`), and the plain first-order measure at `params`. Run
    once, after the solve, where the solver reported such a stop (its stop was at a stall
    either way: only the verdict depends on it), so that the solver's compiled step holds
    no second simulation. (A float32 RC circuit whose columns of R and C shrank 1e8-fold
    in one step read stationary at their largest norm with a loss 7000 times the
    optimum's; a float32 BFGS with a loose step test stopped on noisy data at 20 times the
    optimum's loss, below eps `data_scale`, and read as a zero residual.)"""
    C, g, d_t, d_x = _evaluated(problem, params, strategy)
    down = descends(problem, params, g, Params(d_t, d_x), along, strategy)
    return down, first_order(problem, params, C, g, d_t, d_x)


# `gauss_newton_refutes` forms the whole Jacobian (every trajectory's x0 columns beside
# theta's) up to this many entries; a larger problem is not checked.
CHECK_ENTRIES = 2**22

# `gauss_newton_refutes`: a success is refuted where the Gauss-Newton step from J itself
# moves a quantity the data determine by more than this many of its standard errors.
CHECK_SE = 1.0

# `_fit._settle`: a first-order solver's stall is settled where the Newton step
# (`newton_distance`) is at most this many standard errors (the least-squares solvers'
# default stol, with which they settle a stall inside their loop:
# `AbstractLeastSquares._settled`).
SETTLE_SE = 1e-2


def _whole_jacobian(problem: FitProblem, params: Params, strategy):
    """The linearisation at `params` and its whole Jacobian J (N R, p + N m): theta's
    columns beside every trajectory's x0 columns, block-diagonal over the trajectories."""
    lin = problem.jacobian(params, strategy)
    N, R = lin.r.shape
    p, m = lin.Jt.shape[-1], lin.Jx.shape[-1]
    eye = jnp.eye(N, dtype=lin.r.dtype)[:, None, :, None]
    Jx = (lin.Jx[:, :, None, :] * eye).reshape(N * R, N * m)
    return lin, jnp.concatenate([lin.Jt.reshape(N * R, p), Jx], axis=1)


def gauss_newton_refutes(problem: FitProblem, params: Params, strategy):
    """After a success in a precision below float64: whether the Gauss-Newton step
    computed from the residual Jacobian J itself (Jacobi-scaled) refutes it, and that
    step's size in standard errors.

    The solvers form J^T J (eq. 17/20 give J^T r and J's columns), which squares J's
    condition number: in float32 its eigenvalues below about 1e-4 of the largest are
    round-off (`_linalg.scaled_eigh`'s cut), and a direction the data determine with a
    scaled singular value 1e-2 of the largest is lost. A fit along such a direction
    reads stationary to the precision of its normal equations (a first-order model with
    an output offset, whose input 10 + 0.03 N(0, 1) made the gain, the offset and x0
    nearly collinear, read converged 15.6 standard errors from the optimum, the loss
    1.24 times the optimum's), while J itself resolves it (cond J about 4e3 there).

    The step h = -J^+ r: J = Q R by Householder QR, then the SVD of the triangle R =
    U diag(s) V^T (Golub and Van Loan, "Matrix Computations", 4th ed., 2013, Sec. 5.5),
    singular values below 10 sqrt(columns) eps of the largest cut (J's round-off). It
    predicts the decrease pred = ||U^T Q^T r||^2 over the kept singular
    vectors, and sqrt(pred / sigma^2), sigma^2 = C / (R - rank J), bounds the move of
    every quantity the data determine in its own standard error (`standard_errors`).
    Refuted where that is above `CHECK_SE` and the loss confirms it: at one of the step
    lengths a = 1, 1/2, 1/4 (projected onto the constraints) C falls by at least a
    quarter of its linear model's (2 a - a^2) pred.

    **Returns:** (refuted, the step's size in standard errors, whether J^T J loses a
    direction that J keeps: a kept singular value whose square is at most the null cut
    of `_linalg.scaled_eigh`, 1e3 eps of the largest, and whether J has full rank and
    theta's columns too by themselves, judged in J^T J as the solvers judge them:
    `_linalg.numerical_rank` of J_t^T J_t against its diagonal)."""
    lin, J = _whole_jacobian(problem, params, strategy)
    N = lin.r.shape[0]
    p, m = lin.Jt.shape[-1], lin.Jx.shape[-1]
    dtype = lin.r.dtype
    r = lin.r.reshape(-1)
    d = jnp.sqrt(jnp.sum(J * J, axis=0))
    d = jnp.where(d > 0, d, 1.0)
    # (a tall J: its QR first, then the SVD of the small triangle, R = U s V^T)
    Q, tri = jnp.linalg.qr(J / d)
    U, s, Vt = jnp.linalg.svd(tri, full_matrices=False)
    eps = jnp.finfo(dtype).eps
    # (the cut of J's round-off alone, columnwise relative errors eps: ||dJ|| <= eps
    # sqrt(columns) ||J||; lstsq's max(rows, columns) eps grows with the record and cut a
    # direction 2.7e-4 of the largest at T = 2500)
    kept = s > 10.0 * np.sqrt(J.shape[1]) * eps * jnp.max(s, initial=0.0)
    coef = jnp.where(kept, U.T @ (Q.T @ r), 0.0)
    pred = jnp.sum(coef**2)
    C = jnp.sum(r * r)
    rank = jnp.sum(kept)
    se = standard_errors(pred, C, n_observations(problem), rank)
    h = -(Vt.T @ (coef / jnp.where(kept, s, 1.0))) / d
    h_t, h_x = h[:p], h[p:].reshape(N, m)

    def objective(q):
        return problem.loss(q, strategy) + problem.g(q.theta)

    here = objective(params)

    def confirms(a):
        theta = params.theta + a * h_t
        if p and (problem.constrained or problem.regulariser is not None):
            theta = problem.feasible(theta)
        there = objective(Params(theta, problem.feasible_x0(params.x0 + a * h_x)))
        model = (2.0 * a - a * a) * pred / jnp.maximum(C, jnp.finfo(dtype).tiny)
        return jnp.isfinite(there) & (here - there >= 0.25 * model * jnp.abs(here))

    alphas = jnp.asarray((1.0, 0.5, 0.25), dtype)
    confirmed = jnp.any(jax.lax.map(confirms, alphas))
    lost = jnp.any(kept & (s**2 <= NULL_CUT * eps * jnp.max(s, initial=0.0) ** 2))
    alone = jnp.array(True)
    if p:  # (theta's columns alone; none in an x0-only fit)
        Jt = lin.Jt.reshape(-1, p)
        A = Jt.T @ Jt
        alone = numerical_rank(A, jnp.diag(A)) == p
    regular = (rank == J.shape[1]) & alone
    return (se > CHECK_SE) & confirmed & jnp.isfinite(here), se, lost, regular


# `newton_distance` forms the loss's Hessian (a forward derivative of the gradient per
# column) for at most this many free variables; a larger problem is not checked.
NEWTON_COLUMNS = 256


def newton_distance(problem: FitProblem, params: Params, strategy, held):
    """The Newton step from `params` in standard errors, and whether it is defined: for a
    stall that the Gauss-Newton step settled (`AbstractLeastSquares._settled`, and
    `_fit._settle` after a first-order solver), where the loss's curvature need not be
    J^T J's. With C = ||r||^2 (eq. 5/21), grad C = 2 J^T r (eq. 17/20, the one-shot
    recursion) and its Hessian H = 2 (J^T J + sum_i r_i Hess r_i), formed as the forward
    derivative of that gradient, the step is d = -H^-1 grad C and its size
    sqrt(||J d||^2 / sigma^2) (`standard_errors`): the distance to the optimum of the
    loss's quadratic model, in the metric of the standard errors. Where the residuals'
    curvature cancels most of J^T J (a structured misfit: H = 0.002 * 2 J^T J along one
    parameter), the Gauss-Newton step (J^T J)^-1 J^T r is that fraction of d: a fit
    stalled 0.6 standard errors from the optimum with a Gauss-Newton step of 1e-3.

    `held`: boolean (p,) theta columns held at a bound (the step of the others, an
    active set). Columns of J that are exactly zero (an initial state that never reaches
    the outputs) are left out with them. Defined where the kept columns have full rank
    and H restricted to them is positive definite (Jacobi-scaled, eigenvalues above the
    null cut `NULL_CUT` eps of the largest; a saddle or a flat direction has no Newton
    step to measure).

    **Returns:** (the step's size in standard errors, whether it is defined, whether the
    nonzero columns of J, the held ones included, have full rank by the same cut: every
    variable that reaches the outputs identifiable at `params`)."""
    lin, J = _whole_jacobian(problem, params, strategy)
    N = lin.r.shape[0]
    p, m = lin.Jt.shape[-1], lin.Jx.shape[-1]
    dtype = lin.r.dtype
    norms = jnp.sqrt(jnp.sum(J * J, axis=0))
    keep = jnp.concatenate([~held, jnp.ones(N * m, bool)]) & (norms > 0)

    def gradient(flat):
        _, g = problem.value_and_grad(Params(flat[:p], flat[p:].reshape(N, m)), strategy)
        return jnp.concatenate([g.theta, g.x0.reshape(-1)])

    flat = jnp.concatenate([params.theta, params.x0.reshape(-1)])
    g = gradient(flat)
    H = jax.jacfwd(gradient)(flat)
    H = 0.5 * (H + H.T)
    eye_n = jnp.eye(J.shape[1], dtype=dtype)
    eps = jnp.finfo(dtype).eps
    # J^T J Jacobi-scaled over the nonzero columns (the held ones too: a variable at its
    # bound still moves the outputs), and over the kept ones alone: held columns get a
    # unit diagonal apart from the rest, and no gradient.
    reach = norms > 0
    scale = jnp.where(reach, norms, 1.0)
    whole = jnp.where(
        reach[:, None] & reach[None, :], (J.T @ J) / (scale[:, None] * scale[None, :]), eye_n
    )
    d = jnp.where(keep, norms, 1.0)
    mask = keep[:, None] & keep[None, :]
    A = jnp.where(mask, whole, eye_n)
    Hs = jnp.where(mask, H / (d[:, None] * d[None, :]), 2.0 * eye_n)
    gs = jnp.where(keep, g / d, 0.0)
    a = jnp.linalg.eigvalsh(A)
    lam, V = jnp.linalg.eigh(Hs)
    regular = a[0] > NULL_CUT * eps * a[-1]
    convex = lam[0] > NULL_CUT * eps * jnp.abs(lam[-1])
    w = jnp.linalg.eigvalsh(whole)
    identifiable = w[0] > NULL_CUT * eps * w[-1]
    step = -(V @ ((V.T @ gs) / jnp.where(convex, lam, 1.0))) / d
    Jd = J @ jnp.where(keep, step, 0.0)
    C = jnp.sum(lin.r * lin.r)
    rank = jnp.sum(keep)
    se = standard_errors(jnp.sum(Jd * Jd), C, n_observations(problem), rank)
    return se, regular & convex & jnp.all(jnp.isfinite(H)), identifiable


def first_order_at(problem: FitProblem, params: Params, strategy):
    """The first-order measure at `params`, from the gradient and the Jacobian's column
    norms evaluated there, and whether the residual is zero there (`zero_residual`, where
    the measure says nothing): for a success claimed by a solver that reports no measure
    of its own (one written by a user, whose `measures` are `no_measures`), measured
    after the solve, as `refuted` is."""
    C, g, d_t, d_x = _evaluated(problem, params, strategy)
    fo = first_order(problem, params, C, g, d_t, d_x)
    return fo, zero_residual(C, data_scale(problem))


def _evaluated(problem: FitProblem, params: Params, strategy):
    """C, half its gradient (J^T r) and diag(J^T J) at `params`."""
    C, grad = problem.value_and_grad(params, strategy)
    d_t, d_x = column_norms(problem, params, strategy)
    return C, Params(0.5 * grad.theta, 0.5 * grad.x0), d_t, d_x


def _output_scales(z, m, sqrt_q, s, xp):
    """Per output (of Q^{1/2} z times the loss's scaling `s`): the loss of predicting its
    mean, sum over the counted samples (mask `m`, or None) of (s Q^{1/2} (z_k - zbar))_j^2,
    plus 100 eps times the loss of predicting it zero (its own round-off: an RMS
    residual of 10 eps |z_j|), (n_z,). `xp`: `jax.numpy` (traced) or `numpy` (on the
    host, where `fit` checks a result without compiling)."""
    axes = tuple(range(z.ndim - 1))
    if m is None:
        dev, zm = z - xp.mean(z, axis=axes), z
    else:
        zbar = xp.sum(z * m, axis=axes) / xp.maximum(xp.sum(m, axis=axes), 1)
        dev, zm = (z - zbar) * m, z * m
    w, v = weigh(dev, sqrt_q) * s, weigh(zm, sqrt_q) * s
    eps = xp.finfo(xp.result_type(w)).eps
    return xp.sum(w * w, axis=axes) + 100.0 * eps * xp.sum(v * v, axis=axes)


def data_scale(problem: FitProblem):
    """The scale against which a zero residual is judged (`zero_residual`): the loss of
    predicting each output's mean, sum over the counted samples of ||Q^{1/2} (z_k -
    zbar)||^2 / T, plus 100 eps times the loss of predicting zero outputs (the round-off
    of the outputs themselves: an RMS residual of 10 eps |z|), the outputs' scales
    (`_output_scales`) summed. The variation and not |z| itself: an output with a large
    offset (a temperature in kelvin, 300 + 0.05 x) made a fit stalled at FIT 8 % look
    exact. Summed over the outputs, it is the solvers' test (they hold C alone); `fit`
    checks a zero residual per output after the solve (`outputs_above_round_off`)."""
    sqrt_q, s = problem.cost.sqrt_weight(), problem._scale()
    return jnp.sum(_output_scales(problem.z, _measured(problem), sqrt_q, s, jnp))


def outputs_above_round_off(problem: FitProblem, e) -> np.ndarray:
    """Which outputs' residuals `e` (zhat - z, the shape of the problem's z; NaN where not
    measured) are not at the round-off level of that output (`zero_residual` of each
    output alone: its sum of squared residuals against its own `_output_scales`,
    unweighted, since a weight's cross terms would mix the outputs' sizes), (n_z,)
    booleans, False for an output of weight 0 (not fitted). On the host (NumPy: no
    program to compile). A zero residual of the outputs together can hide one: a fixed
    term reproducing an output of size 1e14 exactly made eps `data_scale` 1e12, and a
    second output, of size 1 and NRMSE 0.5, read as exact."""
    z = np.asarray(problem.z)
    m = None
    if problem.mask is not None:
        out = np.asarray(problem.mask.outputs)
        m = np.broadcast_to(out if out.ndim == z.ndim else out[..., None], z.shape)
    e = np.where(np.isfinite(e), np.asarray(e, z.dtype), 0.0)
    e = e if m is None else e * m
    axes = tuple(range(z.ndim - 1))
    eps = np.finfo(z.dtype).eps
    above = np.sum(e * e, axis=axes) > ZERO_RESIDUAL_RTOL * eps * _output_scales(
        z, m, None, 1.0, np
    )
    seen = problem.cost.observed()
    return above if seen is None else above & np.asarray(seen)


def zero_residual(C, scale):
    """Whether C is at the round-off level of the data: 0 <= C <= eps `data_scale` (a
    relative RMS residual of sqrt(eps) of the outputs' variation). Not where C < 0 (a
    signed penalty of a first-order solver): that says nothing of the residuals."""
    eps = jnp.finfo(jnp.result_type(C)).eps
    return (C >= 0) & (C <= ZERO_RESIDUAL_RTOL * eps * scale)


def promises_descent(problem: FitProblem, C, fo):
    """Whether the first-order measure `fo` at a loss C promises a decrease of C beyond its
    round-off (`descends`'s bound SAME_PATH eps (sqrt(C Z) + C), Z the outputs'
    `output_norm`): fo^2 C, the decrease of the Gauss-Newton step along the column of the
    largest cosine alone, above it. Where it does not, a zero-residual stop stands without
    `refuted`'s check: at round-off residuals, C about (k eps)^2 Z, it cannot for k up to
    SAME_PATH. Traced, inside the fit's compiled call: the check it spares is a second
    program."""
    eps = jnp.finfo(problem.dtype).eps
    C = jnp.abs(C)
    bound = SAME_PATH * eps * (jnp.sqrt(C * output_norm(problem)) + C)
    return ~(fo**2 * C <= bound)  # (NaN fo: a solver without the measure, checked)


def output_norm(problem: FitProblem):
    """The loss of predicting zero outputs, sum over the counted samples of ||Q^{1/2}
    z_k||^2 / T (in the loss's weights and scaling): the squared size of the outputs,
    whose precision bounds that of the residuals (`stall_limit`)."""
    z, m = problem.z, _measured(problem)
    z = z if m is None else z * m
    v = weigh(z, problem.cost.sqrt_weight()) * problem._scale()
    return jnp.sum(v * v)


def column_norms(problem: FitProblem, params: Params, strategy, *, dense_max=256, probes=16):
    """diag(J^T J) of the residual Jacobian at `params`: of the theta columns (p,) and of
    each trajectory's x0 columns (N, m).

    The x0 columns are formed (`x0_columns`). The theta columns are formed too while
    p <= `dense_max` and the dense Jacobian fits (`_strategy.dense_jacobian_fits`);
    otherwise the diagonal is estimated (`rademacher_diagonal`).
    """
    p = params.theta.shape[0]
    if p <= dense_max and dense_jacobian_fits(problem, p + params.x0.shape[-1]):
        lin = problem.jacobian(params, strategy)
        return jnp.sum(lin.Jt**2, axis=(0, 1)), jnp.sum(lin.Jx**2, axis=1)
    r, _, traj = problem.linearise(params, strategy)
    Jx = x0_columns(problem, params, traj, strategy)  # (m, N, R)
    d_x = jnp.moveaxis(jnp.sum(Jx**2, axis=-1), 0, -1)
    return rademacher_diagonal(problem, params, traj, r, strategy, probes), d_x


def x0_columns(problem: FitProblem, params: Params, traj, strategy):
    """The Jacobian's x0 columns at the linearisation `traj`: m forward sensitivities
    (eq. (17)/(20)'s forward twin, `FitProblem.jvp`), direction e_j in every trajectory's
    x0 at once.

    **Returns:**

    (m, N, R): column j of each trajectory's residual Jacobian J_x,i.
    """
    p, (N, m) = params.theta.shape[0], params.x0.shape
    dtype = problem.dtype
    zeros_t = jnp.zeros((p,), dtype)
    E_x = np.eye(m, dtype=dtype)
    return jax.vmap(
        lambda e: problem.jvp(params, traj, zeros_t, jnp.broadcast_to(e, (N, m)), strategy)
    )(E_x)


def rademacher_diagonal(problem: FitProblem, params: Params, traj, r, strategy, probes):
    """An estimate of diag(J_t^T J_t) without forming J_t: the mean of (J_t^T w)^2 over
    `probes` Rademacher vectors w (E[(J^T w)(J^T w)^T] = J^T J; Bekas, Kokiopoulou and
    Saad, "An estimator for the diagonal of a matrix", 2007), each J_t^T w one reverse
    product (the one-shot recursion of eq. (17)/(20), `FitProblem.vjp`). Unbiased, and it
    scales with the parameters' units as the exact diagonal does.

    **Arguments:**

    - `problem`, `params`, `traj`, `strategy`: the linearisation (`FitProblem.linearise`).
    - `r`: its residuals (N, R) (their shape and dtype).
    - `probes`: the number of probe vectors (a fixed key: the estimate is deterministic).

    **Returns:**

    (p,) the estimated diagonal.
    """
    signs = jax.random.rademacher(jax.random.PRNGKey(0), (probes, *r.shape), dtype=problem.dtype)
    W = jax.vmap(lambda w: jnp.sum(problem.vjp(params, traj, w, strategy)[0], 0))(signs)
    return jnp.mean(W**2, axis=0)


class Scaling(NamedTuple):
    """Marquardt's diagonal kept by a solver that has no Jacobian at hand (the first-order
    solvers), to estimate the first-order measure at every step from the gradient alone;
    refreshed where the estimate says the test may hold. `top_t`, `top_x`: the largest
    diagonal of each column at the points it was formed at (the start and the refreshes),
    for the test of a stall (`stall_test`)."""

    d_t: jax.Array
    d_x: jax.Array
    top_t: jax.Array
    top_x: jax.Array


def scaling(problem: FitProblem, params: Params, strategy, kept: Scaling | None = None):
    """The `Scaling` at `params`; with `kept`, the largest diagonals carried over."""
    d_t, d_x = column_norms(problem, params, strategy)
    if kept is None:
        return Scaling(d_t, d_x, d_t, d_x)
    return Scaling(d_t, d_x, jnp.maximum(kept.top_t, d_t), jnp.maximum(kept.top_x, d_x))


def check_first_order(
    problem,
    params,
    C,
    grad: Params,
    scale: Scaling,
    stall,
    gtol,
    strategy,
    fresh=False,
    final=False,
):
    """The first-order test of a solver that has the gradient of C only.

    With the kept `scale`, the measure is estimated from `grad` (the gradient of C, twice
    J^T r); where the estimate is at most `gtol`, the solver `stall`s or the step is its
    `final` one (the measure it reports), the diagonal is refreshed at `params` (a
    Jacobian) and the measure recomputed. `fresh=True` (static): `scale` was formed at
    `params`, so the measure is exact as it is (no Jacobian is traced). A positive `gtol`
    counts as at least the `resolution` of the dtype. Returns the measure, whether
    `params` is stationary (the measure at most that `gtol`, or at a stall the test of
    `stall_test`), the scaling to keep, and whether the measure is that of a stall with
    vanished columns.
    """
    gtol = gtol_at_least_resolution(gtol, problem.dtype)
    half = Params(0.5 * grad.theta, 0.5 * grad.x0)
    fo = first_order(problem, params, C, half, scale.d_t, scale.d_x)
    if not fresh:
        refresh = (fo <= gtol) | stall | final
        scale = lazy_cond(refresh, lambda: scaling(problem, params, strategy, scale), scale)
        fo = first_order(problem, params, C, half, scale.d_t, scale.d_x)
    met = fo <= gtol
    at_stall, still, degenerate = stall_test(
        problem, params, C, half, scale.d_t, scale.d_x, scale.top_t, scale.top_x, fo
    )
    degenerate = stall & ~met & degenerate
    fo = jnp.where(degenerate, at_stall, fo)
    return fo, met | (stall & still), scale, degenerate


def lazy_cond(pred, true_fn, false_value):
    """`true_fn()` where `pred`, else `false_value`, evaluating `true_fn` only when `pred`
    holds. Under `vmap` (the starts of a multistart fit) a `lax.cond` with a batched
    predicate evaluates both branches; a while loop runs its body only while some start
    needs it."""

    def body(c):
        return jnp.array(False), true_fn()

    return jax.lax.while_loop(lambda c: c[0], body, (pred, false_value))[1]
