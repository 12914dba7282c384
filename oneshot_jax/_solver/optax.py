"""First-order solvers: Algorithm 1 of the paper with any optax transform, Adam, L-BFGS.

Each step evaluates C and its one-shot closed-form gradient (eq. 17, 20) at the current
iterate, hands the gradient to the optax transform, applies the update and projects theta
back onto the constraint set (Section 3.3), so every iterate is feasible. The transform
sees the free variables as the dict `{"theta": p_theta, "x0": p_x0}`, so a transform can
treat them differently (`optax.partition`, as `Adam` does).

Stopping: the first-order test of every solver of `fit` (`gtol`, see
`oneshot_jax._optimality`; success), and Algorithm 1's tests, line 3: `tol_loss`
(epsilon; off by default, since a loss with a signed penalty can be negative) and
`tol_grad` (delta, an unscaled gradient norm; off by default). The first-order measure
needs Marquardt's diagonal diag(J^T J), which a first-order solver does not have: it is
computed at the start (one Jacobian, or a 16-probe estimate above 256 free entries) and
again wherever the estimate from the kept diagonal passes the test, so the test that
ends a fit is exact at the returned point. `LBFGS` is monotone: a step that does not
decrease the loss is not taken; it tries once more from a fresh memory and then stops
(`stalled`, or converged where the measure is below its round-off limit, with the
columns that vanished along the fit measured at their largest norm:
`_optimality.stall_test`). With
constraints its quasi-Newton model covers the free entries only: the entries that a
projected diagonal-Newton step leaves at their bound get a zero gradient, and the memory
starts afresh when that set changes. A non-finite loss or gradient stops with
`RESULTS.diverged` and returns the last finite iterate. Otherwise the solver runs to
`max_steps` (`max_steps_reached`, not a success).

A proximal regulariser g (`oneshot_jax.sparsity.l1`, `group_lasso`, given in
`fit(regulariser=...)`) turns each step into a proximal-gradient step on C + g: the prox
of g with the step's own step sizes, then the projection (Parikh and Boyd, "Proximal
algorithms", 2014, Sec. 4.2). `Adam` uses its per-coordinate steps
d_i = lr_theta / (max(sqrt(v_hat_i), lambda) + eps) (`proximal_adam`: the prox
in Adam's diagonal metric, whose fixed points are the stationary points of C + g);
`Optax(transform)` uses the regulariser's `learning_rate` (exact for `optax.sgd` with that
rate). The loss recorded and returned is then the objective C + g; the gradient norm is
that of C. `LBFGS` (a smooth line search) refuses a regulariser.
"""

import numbers
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._counts import integral, real
from .._linalg import floor
from .._optimality import (
    Measures,
    Scaling,
    check_first_order,
    data_scale,
    output_norm,
    scaling,
    stall_limit_of,
    vanished_columns,
    zero_residual,
)
from .._problem import FitProblem, Params
from .._prox import (
    ProximalTransformation,
    check_learning_rate,
    check_non_negative_scalar,
    check_schedule,
    step_at,
)
from .._results import RESULTS
from .._strategy import as_strategy
from .base import AbstractSolver, check_options, grad_norm, is_real


class _OptaxState(NamedTuple):
    opt_state: Any
    loss: jax.Array  # the objective C + g at the current iterate (C without a regulariser)
    smooth: jax.Array  # C at the current iterate
    grad: Params  # the gradient of C
    last: Params  # the last iterate with a finite loss and gradient
    last_loss: jax.Array
    count: jax.Array  # updates made (for the regulariser's learning-rate schedule)
    scale: Scaling  # Marquardt's diagonal for the first-order measure
    data: jax.Array  # the scale of a zero residual (`_optimality.data_scale`)
    outputs: jax.Array  # the loss of predicting zero outputs (`_optimality.output_norm`)
    first_order: jax.Array  # the first-order measure at the current iterate
    stationary: jax.Array
    degenerate: jax.Array  # whether that measure is a stall's with vanished columns
    stalls: jax.Array  # (LBFGS) consecutive steps that did not decrease the loss
    held: Params  # (LBFGS) entries of theta and x0 held by the constraints at the last step


def _as_dict(p: Params):
    return {"theta": p.theta, "x0": p.x0}


def _as_params(d) -> Params:
    return Params(d["theta"], d["x0"])


def _check_updates(updates, params):
    """Raise a ValueError (while tracing) unless an optax transform's `updates` have the
    structure and shapes of the parameter dict it was given: `apply_updates` would
    otherwise fail deep inside JAX, or broadcast."""
    want = jax.tree_util.tree_map(jnp.shape, params)
    try:
        got = jax.tree_util.tree_map(jnp.shape, updates)
    except (TypeError, ValueError):
        got = updates
    if got != want:
        raise ValueError(
            "`Optax(transform)`: the transform's update must have the structure and shapes "
            f"of the parameters it is given, {want} (theta's free entries flat, one x0 "
            f"row per trajectory), got {got}."
        )


class _ClosedFormLoss(eqx.Module):
    """C at the projected point as a function of the optax parameter dict, whose gradient
    (for line searches that call `jax.value_and_grad` on it) is the one-shot closed form."""

    problem: FitProblem
    strategy: str

    def __call__(self, d):
        return _loss_with_closed_form_grad(d, self.problem, self.strategy)


def _make_loss():
    def value(d, problem, strategy):
        p = Params(problem.feasible(d["theta"]), problem.feasible_x0(d["x0"]))
        return problem.value_and_grad(p, strategy)

    @eqx.filter_custom_vjp
    def loss(d, problem, strategy):
        return value(d, problem, strategy)[0]

    @loss.def_fwd
    def loss_fwd(perturbed, d, problem, strategy):
        del perturbed
        C, g = value(d, problem, strategy)
        return C, g

    @loss.def_bwd
    def loss_bwd(g, ct, perturbed, d, problem, strategy):
        del perturbed, d, problem, strategy
        return {"theta": ct * g.theta, "x0": ct * g.x0}

    return loss


_loss_with_closed_form_grad = _make_loss()


class _AbstractOptax(AbstractSolver):
    """Algorithm 1 around an optax transform (built by `_transform`)."""

    max_steps: eqx.AbstractVar[int]
    tol_loss: eqx.AbstractVar[float | None]
    tol_grad: eqx.AbstractVar[float]
    gtol: eqx.AbstractVar[float]
    strategy: eqx.AbstractVar[str]

    TRACED_OPTIONS = ("tol_loss", "tol_grad", "gtol")
    TRACED_INTEGERS = ("max_steps",)
    GTOL_AT_LEAST_RESOLUTION = True

    # A monotone method (LBFGS's line search) rejects a step that does not decrease the
    # objective and stops there (a stall); Adam's steps may go up and down.
    _monotone = False

    def _transform(self, problem: FitProblem) -> optax.GradientTransformation:
        raise NotImplementedError

    def _prox(self, problem: FitProblem, p_theta, count):
        """The proximal step of the regulariser and the projection after an update: the
        projection alone by default (the transform applies the prox itself)."""
        del count
        return problem.feasible(p_theta)

    def _check(self):
        check_options(
            self, non_negative=("tol_grad",), fractions=("gtol",), integers=("max_steps",)
        )
        if self.tol_loss is not None and not is_real(self.tol_loss):
            raise ValueError(
                f"`{type(self).__name__}(tol_loss=...)` must be a finite number or None (off), "
                f"got {self.tol_loss!r}."
            )
        as_strategy(self.strategy, f"`{type(self).__name__}(strategy=...)`")

    def _check_tol_grad(self):
        """Refuse `tol_grad` with a regulariser: ||grad C|| is not small at the optimum of
        C + g (where grad C = -a subgradient of g), and small where the regulariser has not
        acted yet (Adam with l1 from the least-squares point stopped at step 0 as a
        success, every term still in)."""
        tol = self.tol_grad
        if isinstance(tol, numbers.Real) and not isinstance(tol, bool) and tol > 0:
            raise ValueError(
                f"`tol_grad` ({tol!r}) tests ||grad C||, which is not small at the optimum "
                "of C + g with a regulariser (and is small where the regulariser has not "
                "acted yet): leave tol_grad at 0 with `regulariser=`; the first-order test "
                "(`gtol`) measures the proximal step's stationarity."
            )

    def init(self, problem, params):
        C, g = problem.value_and_grad(params, self.strategy)
        opt_state = self._transform(problem).init(_as_dict(params))
        obj = C + problem.g(params.theta)
        scale = scaling(problem, params, self.strategy)
        no = jnp.array(False)
        fo, stationary, scale, degenerate = check_first_order(
            problem, params, C, g, scale, no, self.gtol, self.strategy, fresh=True
        )
        zero = jnp.array(0, jnp.int32)
        held = Params(jnp.zeros(params.theta.shape, bool), jnp.zeros(params.x0.shape, bool))
        return _OptaxState(
            opt_state,
            obj,
            C,
            g,
            params,
            obj,
            zero,
            scale,
            data_scale(problem),
            output_norm(problem),
            fo,
            stationary,
            degenerate,
            zero,
            held,
        )

    def _held(self, problem, params, grad, scale):
        """Entries of theta that the constraints hold where they are, and of x0 that its
        box holds (`Params` of masks): a projected
        diagonal-Newton step P(theta - grad C / (2 d^2)) leaves them in place although
        their gradient is not zero (at a bound that the gradient pushes against). Only
        where the projection moved the step: an entry whose step is below its round-off
        (a large column's, next to one 1e7 times smaller) is not held, which reset the
        memory and stalled L-BFGS with an inactive box."""
        eps = jnp.finfo(problem.dtype).eps

        def held(x, g, d, project):
            step = x - 0.5 / floor(d) * g
            trial = project(step)
            return (trial != step) & (jnp.abs(trial - x) <= 4 * eps * jnp.abs(x)) & (g != 0)

        t = jnp.zeros(params.theta.shape, bool)
        if problem.constrained:
            t = held(params.theta, grad.theta, scale.d_t, problem.feasible)
        x = jnp.zeros(params.x0.shape, bool)
        if problem.x0_bounded:  # (the box of x0: held like theta's)
            x = held(params.x0, grad.x0, scale.d_x, problem.feasible_x0)
        return Params(t, x)

    def step(self, problem, params, state):
        tx = self._transform(problem)
        d = _as_dict(params)
        opt_state, held = state.opt_state, state.held
        grad = state.grad
        if self._monotone:
            # A quasi-Newton model of the free entries only: the gradient of the entries
            # that the constraints hold is zero for it, and its memory starts afresh when
            # that set changes or after a step that did not decrease the loss.
            held = self._held(problem, params, grad, state.scale)
            grad = Params(jnp.where(held.theta, 0.0, grad.theta), jnp.where(held.x0, 0.0, grad.x0))
            changed = jnp.any(held.theta != state.held.theta) | jnp.any(held.x0 != state.held.x0)
            reset = (state.stalls > 0) | changed
            fresh = tx.init(d)
            opt_state = jax.tree_util.tree_map(
                lambda a, b: jnp.where(reset, a, b) if eqx.is_array(a) else b,
                fresh,
                opt_state,
            )
        g = _as_dict(grad)
        if isinstance(tx, optax.GradientTransformationExtraArgs):
            value_fn = _ClosedFormLoss(problem, self.strategy)
            updates, opt_state = tx.update(
                g, opt_state, d, value=state.smooth, grad=g, value_fn=value_fn
            )
        else:
            updates, opt_state = tx.update(g, opt_state, d)
        _check_updates(updates, d)
        new = _as_params(optax.apply_updates(d, updates))
        new = Params(self._prox(problem, new.theta, state.count), problem.feasible_x0(new.x0))
        C, g_new = problem.value_and_grad(new, self.strategy)
        obj = C + problem.g(new.theta)
        finite = jnp.isfinite(obj) & jnp.isfinite(grad_norm(g_new))
        stall = jnp.array(False)
        stalls = state.stalls
        if self._monotone:
            # No decrease: keep the current iterate; try once more from a fresh memory,
            # and stop after a second such step.
            stall = finite & ~(obj < state.loss)
            keep = lambda a, b: jax.tree_util.tree_map(  # noqa: E731
                lambda x, y: jnp.where(stall, x, y), a, b
            )
            new, C, g_new, obj = keep(
                (params, state.smooth, state.grad, state.loss), (new, C, g_new, obj)
            )
            stalls = jnp.where(stall, stalls + 1, 0)
        last = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), new, state.last)
        last_loss = jnp.where(finite, obj, state.last_loss)
        count = optax.safe_increment(state.count)
        # The last step's measure is exact (the one reported): at max_steps, and where
        # tol_loss or tol_grad stop the fit.
        small_loss, small_grad = self._thresholds(obj, grad_norm(g_new))
        final = (count >= self.max_steps) | small_loss | small_grad
        fo, stationary, scale, degenerate = check_first_order(
            problem, new, C, g_new, state.scale, stall, self.gtol, self.strategy, final=final
        )
        return new, _OptaxState(
            opt_state,
            obj,
            C,
            g_new,
            last,
            last_loss,
            count,
            scale,
            state.data,
            state.outputs,
            fo,
            stationary,
            degenerate,
            stalls,
            held,
        )

    def _thresholds(self, loss, gnorm):
        """Whether the user's thresholds hold (Algorithm 1's epsilon and delta): the
        objective below `tol_loss`, the gradient norm below `tol_grad`."""
        small_loss = jnp.array(False) if self.tol_loss is None else loss < self.tol_loss
        return small_loss, gnorm < self.tol_grad

    def terminate(self, problem, params, state):
        del params
        gnorm = grad_norm(state.grad)
        finite = jnp.isfinite(state.loss) & jnp.isfinite(gnorm)
        small_loss, small_grad = self._thresholds(state.loss, gnorm)
        stalled = (state.stalls >= 2) & ~state.stationary
        # At the last step allowed, a loss at the round-off level of the data is a
        # solution, not `max_steps_reached` (an exact fit of outputs of size 1e-6 said
        # "raise max_steps"; `_fit` then checks that no step still lowers the loss
        # beyond round-off). Not before: a first-order step there still moves the
        # parameters by more than the outputs resolve. With a regulariser g, never: C at
        # round-off says nothing of C + g (lambda 1e-9 keeps the optimum's C in the band,
        # and a dense exact fit is there too).
        zero = zero_residual(state.smooth, state.data) & (problem.regulariser is None)
        result = RESULTS.where(zero, RESULTS.zero_residual, RESULTS.stalled)
        zero = zero & (state.count >= self.max_steps)
        result = RESULTS.where(state.stationary, RESULTS.converged, result)
        result = RESULTS.where(small_grad, RESULTS.tol_grad, result)
        result = RESULTS.where(small_loss, RESULTS.tol_loss, result)
        result = RESULTS.where(~finite, RESULTS.diverged, result)
        done = (~finite) | small_loss | small_grad | state.stationary | stalled | zero
        return done, result

    def summary(self, state):
        return state.loss, grad_norm(state.grad)

    def measures(self, state):
        nan = jnp.full_like(state.loss, jnp.nan)
        sc = state.scale
        gone = vanished_columns(sc.d_t, sc.top_t, sc.d_x, sc.top_x)[0]
        # At a non-finite loss or gradient (a diverged fit) the measure divides by an
        # infinite ||r|| and reads 0: it measures nothing there, report NaN.
        finite = jnp.isfinite(state.loss) & jnp.isfinite(grad_norm(state.grad))
        fo = jnp.where(finite, state.first_order, nan)
        limit = stall_limit_of(state.smooth.dtype, state.outputs, state.smooth)
        return Measures(fo, nan, nan, nan, jnp.array(False), state.degenerate, gone, limit)

    def postprocess(self, problem, params, state, result):
        del problem
        diverged = result == RESULTS.diverged
        params = jax.tree_util.tree_map(lambda a, b: jnp.where(diverged, a, b), state.last, params)
        loss = jnp.where(diverged, state.last_loss, state.loss)
        return params, loss, None


class Optax(_AbstractOptax):
    """Algorithm 1 of the paper with any optax transform.

    The transform receives the closed-form gradient of C in the free variables as the
    dict `{"theta": ..., "x0": ...}`. Transforms that take extra arguments (line searches,
    `optax.lbfgs`) also get `value`, `grad` and `value_fn`, where `value_fn`'s gradient is
    the closed form too.

    With a regulariser g in `fit(regulariser=...)`, each update is followed by the prox of
    g with step `learning_rate` (the regulariser's, e.g. `l1(lam, where,
    learning_rate=eta)`, or an optax schedule of the update count): with
    `optax.sgd(eta)` this is proximal gradient descent (ISTA) on C + g. For Adam's
    per-coordinate steps use `Adam`, which matches the prox to them.

    **Arguments:**

    - `transform`: an `optax.GradientTransformation`.
    - `max_steps`: the number of updates (E_max).
    - `tol_loss`: stop when C < tol_loss (epsilon); None (default) never.
    - `tol_grad`: stop when ||grad C|| < tol_grad (delta); 0 (default) never. Not with
        a regulariser (a ValueError: ||grad C|| is not small at the optimum of C + g).
    - `gtol`: the first-order test: stop (converged) when the scaled projected
        gradient, the largest cosine between the residual and a Jacobian column, is at
        most `gtol` (see `oneshot_jax._optimality`; estimated from the gradient with
        Marquardt's diagonal of the start, recomputed where the estimate passes).
    - `strategy`: how the gradient's per-step Jacobians are formed (`"auto"`,
        `"jacobian"`, `"vjp"`, `"parallel"`; see `oneshot_jax.value_and_grad`).
    """

    transform: optax.GradientTransformation
    max_steps: int = eqx.field(default=1000, converter=integral)
    tol_loss: float | None = eqx.field(default=None, converter=real)
    tol_grad: float = eqx.field(default=0.0, converter=real)
    gtol: float = eqx.field(default=1e-8, converter=real)
    strategy: str = "auto"

    def __check_init__(self):
        if not (hasattr(self.transform, "init") and hasattr(self.transform, "update")):
            raise TypeError(
                f"`Optax(transform=...)` must be an optax.GradientTransformation, "
                f"got {self.transform!r}."
            )
        self._check()

    def _transform(self, problem):
        del problem
        return self.transform

    def check_regulariser(self, regulariser):
        self._check_tol_grad()
        if regulariser.learning_rate is None:
            raise ValueError(
                "`Optax(transform)` applies the regulariser's prox after each update with "
                "the regulariser's `learning_rate` (the step size of `transform`), which "
                "was not given (or differs between the terms): e.g. "
                "l1(lam, where, learning_rate=eta) with optax.sgd(eta). Or use "
                "oneshot_jax.Adam, which applies the prox with its own per-coordinate steps."
            )

    def _prox(self, problem, p_theta, count):
        """The prox of the regulariser plus the set's indicator at the transform's one
        step size (`FitProblem.prox_feasible`: proximal gradient descent on C + g over
        the set, with `optax.sgd`)."""
        rate = problem.regulariser.learning_rate if problem.regulariser is not None else None
        if rate is None:
            return problem.feasible(p_theta)
        return problem.prox_feasible(p_theta, step_at(rate, count))[0]


class Adam(_AbstractOptax):
    """Algorithm 1 of the paper: Adam (its step 7, in place of the gradient steps of
    eq. 8-9) with separate learning rates for theta and x0, on the one-shot closed-form
    gradient.

    With a regulariser g (`sparsity.l1`, `group_lasso`, `l2`) in `fit(regulariser=...)`, theta
    takes proximal Adam steps (`proximal_adam`): with Adam's bias-corrected
    moments m_hat, v_hat, theta+ = prox_{g, D}(theta - D m_hat), D = diag(d),
    d_i = lr_theta / (max(sqrt(v_hat_i), lambda) + eps), lambda the regulariser's
    strength (the largest one of a combination). The prox in this metric soft-thresholds
    coordinate i at d_i lambda, so selected terms land exactly on zero and stay there
    while Adam's averaged gradient |m_hat_i| <= lambda (the momentum of earlier, larger
    gradients can carry a zero away although |dC/dtheta_i| <= lambda now); the fixed
    points are the stationary points of C + g.
    The floor lambda on sqrt(v_hat) keeps every move at most about lr_theta (it also
    applies to the unregularised entries of theta). x0 takes plain Adam steps.

    **Arguments:**

    - `lr_theta`, `lr_x0`: the learning rates eta_theta and eta_x0 (numbers, or optax
        schedules `count -> rate`, e.g. `optax.cosine_decay_schedule(1e-2, 2000)`).
    - `b1`, `b2`, `eps`: Adam's moment decay rates and denominator offset.
    - `scale`: None (one rate for every entry of theta), or `"theta0"`: the named
        parameters (theta's entries outside equinox modules) take steps relative to their
        starting magnitude, d_i = lr_theta |theta0_i| m_hat_i / (sqrt(v_hat_i) + eps)
        (|theta0_i| = 0 counts as 1), so that lr_theta is a relative rate for them, while
        a network's weights keep the absolute rate. This is Adam on the parameters
        theta_i / |theta0_i| (up to eps): physical parameters of scale 0.05 and 15 then
        move at the same relative pace. theta0 is where this solver starts: each start of
        a multistart its own, and after another solver of a sequence, where that one
        stopped. Not with a regulariser.
    - `max_steps`, `tol_loss`, `tol_grad`, `gtol`, `strategy`: as for `Optax`.
    """

    lr_theta: Any = eqx.field(default=1e-3, converter=real)
    lr_x0: Any = eqx.field(default=1e-4, converter=real)
    b1: float = eqx.field(default=0.9, converter=real)
    b2: float = eqx.field(default=0.999, converter=real)
    eps: float = eqx.field(default=1e-8, converter=real)
    max_steps: int = eqx.field(default=5000, converter=integral)
    tol_loss: float | None = eqx.field(default=None, converter=real)
    tol_grad: float = eqx.field(default=0.0, converter=real)
    gtol: float = eqx.field(default=1e-8, converter=real)
    strategy: str = "auto"
    scale: str | None = None

    def __check_init__(self):
        rates = []  # (the numbers among them; a schedule is checked as one)
        for f in ("lr_theta", "lr_x0"):
            if callable(getattr(self, f)):
                check_schedule(getattr(self, f), f"`Adam({f}=...)`")
            else:
                rates.append(f)
        check_options(self, non_negative=rates, positive=("eps",), fractions=("b1", "b2"))
        if self.scale not in (None, "theta0"):
            raise ValueError(f"`Adam(scale=...)` must be None or 'theta0', got {self.scale!r}.")
        self._check()

    def check_regulariser(self, regulariser):
        del regulariser
        self._check_tol_grad()
        if self.scale is not None:
            raise ValueError(
                "`Adam(scale='theta0')` does not take a regulariser (its prox is written in "
                "Adam's own metric): use scale=None with `regulariser=`."
            )

    def _transform(self, problem):
        x0_tx = optax.adam(self.lr_x0, self.b1, self.b2, self.eps)
        if problem.regulariser is None:
            theta_tx = optax.adam(self.lr_theta, self.b1, self.b2, self.eps)
            if self.scale == "theta0":
                theta_tx = optax.chain(theta_tx, _scale_by_start(problem.nuisance))
            return optax.partition({"theta": theta_tx, "x0": x0_tx}, {"theta": "theta", "x0": "x0"})
        # The regulariser as a prox on the flat free entries (what the transform sees).
        # (with box bounds, whose clip is their prox in Adam's diagonal metric too, the
        # prox of g plus the box's indicator; a general projection's is Euclidean and
        # follows the step, see `fit`'s warning)
        prox = problem.prox
        if problem.project is None:

            def prox(v, steps):
                return problem.prox_feasible(v, steps)[0]

        flat = ProximalTransformation(
            init=None,
            update=None,
            prox=prox,
            value=problem.g,
            strength=problem.regulariser.strength,
        )
        theta_tx = proximal_adam(self.lr_theta, flat, b1=self.b1, b2=self.b2, eps=self.eps)
        return _by_part(theta_tx, x0_tx)


class ProximalAdamState(NamedTuple):
    """Adam's moment estimates (as in `optax.scale_by_adam`) and the update count."""

    count: jax.Array
    mu: Any
    nu: Any


def proximal_adam(
    learning_rate, regulariser, *, b1=0.9, b2=0.999, eps=1e-8, floor=None
) -> optax.GradientTransformation:
    """Adam with a proximal step in its own diagonal metric, for C + g with g non-smooth.

    This is the theta part of `Adam` with a regulariser: the paper's Algorithm 1 (Adam in
    its step 7, in place of the gradient step of eq. 8) with the prox of g where Section
    3.3 puts the projection. With Adam's
    bias-corrected moments m_hat, v_hat (Kingma and Ba 2015, Algorithm 1) and the
    per-coordinate steps

        d_i = eta / (max(sqrt(v_hat_i), floor) + eps),

    the update is theta+ = prox_{g, D}(theta - d * m_hat), D = diag(d): the proximal map
    of g in the metric D^{-1} (`regulariser.prox(params, d)`: soft-thresholding at
    d_i lambda for `l1`; the proximal-gradient method with a diagonal preconditioner, as
    in Yun, Lozano and Yang, "Adaptive proximal gradient methods for structured neural
    networks", NeurIPS 2021). At a fixed point m_hat = grad C and
    theta = prox_{g, D}(theta - D grad C), which holds exactly when 0 is in
    grad C + dg(theta): the fixed points are the stationary points of C + g, whatever the
    steps d. Coordinates that the regulariser does not select take plain (floored) Adam
    steps.

    **The floor.** Adam's move d_i m_hat_i is at most about eta, but the threshold
    d_i lambda is not: with plain Adam steps (`floor=0`) a coordinate whose gradient is far
    below lambda, as all are near a converged fit, is thresholded by
    eta lambda / sqrt(v_hat_i) >> eta in one step and lands on zero however large it is.
    The default floor, the regulariser's `strength` lambda, keeps every move at most about
    eta (the threshold d_i lambda <= eta) and changes no fixed point; below it the step is
    gradient descent with step eta / lambda.

    **Arguments:**

    - `learning_rate`: eta > 0, or an optax schedule `count -> eta`.
    - `regulariser`: a `ProximalTransformation` (`l1`, `group_lasso`, `l2`, or `combine`
        of them; a projection's prox, in a `combine` too, projects whatever the step);
        its own `learning_rate` is not used.
    - `b1`, `b2`, `eps`: as for `optax.adam`.
    - `floor`: the floor on sqrt(v_hat) (>= 0); None takes `regulariser.strength`.

    **Returns:**

    An optax `GradientTransformation`; `update(grads, state, params)` needs `params`.
    """
    check_learning_rate(learning_rate, allow_none=False)
    if not isinstance(regulariser, ProximalTransformation):
        raise ValueError(
            "`regulariser` must be a ProximalTransformation from oneshot_jax.sparsity (l1, "
            f"group_lasso, l2, combine), got {regulariser!r}."
        )
    for name, b in (("b1", b1), ("b2", b2)):
        if not 0 <= b < 1:
            raise ValueError(f"`{name}` must be in [0, 1), got {b!r}.")
    if not eps > 0:
        raise ValueError(f"`eps` must be > 0, got {eps!r}.")
    if floor is None:
        floor = regulariser.strength or 0.0
    check_non_negative_scalar(floor, "floor")

    def init(params):
        zeros = lambda p: jnp.zeros_like(p)  # noqa: E731
        return ProximalAdamState(
            count=jnp.zeros([], jnp.int32),
            mu=jax.tree_util.tree_map(zeros, params),
            nu=jax.tree_util.tree_map(zeros, params),
        )

    def update(grads, state, params=None):
        if params is None:
            raise ValueError("`proximal_adam` needs `params` in `update(grads, state, params)`.")
        count = optax.safe_increment(state.count)
        mu = jax.tree_util.tree_map(lambda m, g: b1 * m + (1 - b1) * g, state.mu, grads)
        nu = jax.tree_util.tree_map(lambda v, g: b2 * v + (1 - b2) * g * g, state.nu, grads)
        eta = step_at(learning_rate, state.count)

        def step(v):  # d_i, in the parameter's dtype
            v_hat = v / (1 - b2 ** count.astype(v.dtype))
            root = jnp.maximum(jnp.sqrt(v_hat), jnp.asarray(floor, v.dtype))
            return jnp.asarray(eta / (root + eps), v.dtype)

        steps = jax.tree_util.tree_map(step, nu)
        moved = jax.tree_util.tree_map(
            lambda p, d, m: p - d * (m / (1 - b1 ** count.astype(m.dtype))), params, steps, mu
        )
        new = regulariser.prox(moved, steps)
        updates = jax.tree_util.tree_map(lambda n, p: n - p, new, params)
        return updates, ProximalAdamState(count=count, mu=mu, nu=nu)

    return optax.GradientTransformation(init, update)


class LBFGS(_AbstractOptax):
    """L-BFGS (optax's, with its zoom line search) on the one-shot closed-form value and
    gradient. Constraints are applied by projecting each accepted point (exact for boxes
    that are inactive at the optimum; prefer the least-squares solvers when bounds are
    active).

    **Arguments:**

    - `memory_size`: the number of past updates kept.
    - `max_linesearch_steps`: the zoom line search's budget per step.
    - `max_steps`, `tol_loss`, `tol_grad`, `gtol`, `strategy`: as for `Optax`
        (defaults 500, None, 0, 1e-8). A step that does not decrease the loss (the line
        search failed) ends the fit: converged where the first-order measure is below
        its round-off limit, stalled otherwise.
    """

    memory_size: int = eqx.field(default=10, converter=integral)
    max_linesearch_steps: int = eqx.field(default=20, converter=integral)
    max_steps: int = eqx.field(default=500, converter=integral)
    tol_loss: float | None = eqx.field(default=None, converter=real)
    tol_grad: float = eqx.field(default=0.0, converter=real)
    gtol: float = eqx.field(default=1e-8, converter=real)
    strategy: str = "auto"

    _monotone = True

    def __check_init__(self):
        check_options(self, integers=("memory_size", "max_linesearch_steps"))
        for field in ("memory_size", "max_linesearch_steps"):
            if getattr(self, field) < 1:
                raise ValueError(
                    f"`LBFGS({field}=...)` must be an integer >= 1, got {getattr(self, field)!r}."
                )
        self._check()

    def _transform(self, problem):
        del problem
        return optax.lbfgs(
            memory_size=self.memory_size,
            linesearch=optax.scale_by_zoom_linesearch(
                max_linesearch_steps=self.max_linesearch_steps, initial_guess_strategy="one"
            ),
        )


class _StartScale(NamedTuple):
    factor: Any  # |theta_i| at the start (1 where it is 0, and for a network's weights)


def _scale_by_start(nuisance) -> optax.GradientTransformation:
    """`Adam(scale="theta0")`'s factors: multiply the updates of theta's free entries
    (within `optax.partition`'s masked dict) by their magnitude at the start of the run,
    |theta_i| (1 where it is 0), and those of a network's weights (`nuisance`) by 1. The
    factors are taken from the parameters `init` is given: each start of a multistart
    its own."""
    nuisance = np.asarray(nuisance, int)

    def factor(start):
        start = jnp.abs(start)
        out = jnp.where(start > 0, start, jnp.ones_like(start))
        return out.at[nuisance].set(1.0) if nuisance.size else out

    def init(params):
        return _StartScale(jax.tree_util.tree_map(factor, params))

    def update(updates, state, params=None):
        del params
        return jax.tree_util.tree_map(lambda a, f: a * f, updates, state.factor), state

    return optax.GradientTransformation(init, update)


def _by_part(theta_tx, x0_tx) -> optax.GradientTransformation:
    """One transform of the dict {"theta", "x0"} from one transform per part."""

    def init(d):
        return {"theta": theta_tx.init(d["theta"]), "x0": x0_tx.init(d["x0"])}

    def update(g, state, d):
        u_t, s_t = theta_tx.update(g["theta"], state["theta"], d["theta"])
        u_x, s_x = x0_tx.update(g["x0"], state["x0"], d["x0"])
        return {"theta": u_t, "x0": u_x}, {"theta": s_t, "x0": s_x}

    return optax.GradientTransformation(init, update)
