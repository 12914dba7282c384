"""The one loop every solver runs in, solver sequences and multistart.

`iterate` runs one solver from S starting points at once as a `lax.while_loop` (see
`oneshot_jax._solver.base` for the interface): every step applies the solver's `step` to
all starts (vmapped) and freezes the ones that have stopped, so the step counter, the
history's bookkeeping and the progress bar are shared and cost nothing per start. `run`
chains a sequence of solvers, each starting where the last stopped; `fit` compiles it as
one call. Side by side (vmapped), every start steps until the last one stops and every
branch of a solver's tests runs for all of them: on a CPU, where a batch of starts saves
little over the starts one by one, `run` takes the starts in turn instead (`lax.scan` of
the whole sequence of solvers, one start each: each stops on its own tests;
`starts_in_turn`; `benchmarks/multistart.py` times both).

With held-out records (`FitProblem.validation`, `oneshot_jax._validation`) the loop
scores every iterate on them, keeps the best one across all solvers and stops a solver
after `patience` scores without improvement.
"""

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _history
from ._optimality import Measures
from ._problem import FitProblem, Params
from ._results import RESULTS, succeeded


class Solution(NamedTuple):
    """What one solver returns from S starts (every field has a leading S axis, but the
    history's shared `step`, `count` and `stride`)."""

    params: Params
    loss: jax.Array
    result: RESULTS
    num_steps: jax.Array
    history: _history.History | None  # None with history_size=0
    final_loss: jax.Array  # the loss and gradient norm at each start's last iterate
    final_grad_norm: jax.Array
    final_theta: jax.Array  # (the last iterate, before `postprocess`)
    blocks: Any  # normal-equation blocks for the covariance, or None
    measures: Measures  # what each start's stop was tested on
    best: Any  # with validation: the `Best` so far (over this and earlier solvers), else None
    solver_result: RESULTS  # each start's own stop, before a validation stop replaced it


class Best(NamedTuple):
    """With validation data: per start, the lowest validation loss so far, its iterate
    and where it was taken (the solver of a sequence and its step, as the history counts
    them), the records' initial states of the last score (the next one's warm start) and
    the scores since it improved."""

    score: jax.Array  # (S,)
    params: Params  # (S, ...)
    val_x0: jax.Array  # (S, N, n_x)
    since: jax.Array  # (S,) int
    here: jax.Array  # (S,) bool: the best iterate is this solver's current one (or ties it)
    last: jax.Array  # (S,) the score of this solver's current iterate
    stage: jax.Array  # (S,) int: the solver of the sequence that took the best iterate
    step: jax.Array  # (S,) int: the step of that solver at which it was taken

    def returned_score(self):
        """The score of the iterate the fit returns: the current one where it is the best
        or ties with it (`here`), else the lowest."""
        return jnp.where(self.here, self.last, self.score)


class _Carry(NamedTuple):
    params: Params
    state: Any  # the dynamic (array) part of the solvers' states
    step: jax.Array  # shared by the starts
    num_steps: jax.Array  # per start: the steps it took before stopping
    done: jax.Array
    result: RESULTS
    history: _history.History | None  # None with history_size=0
    best: Best | None


def _where(pred, a, b):
    """`RESULTS.where` for a batch of starts (a boolean per start)."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


def _freeze(done, old, new):
    """`new` where a start is still running, `old` where it has stopped."""

    def pick(a, b):
        if not eqx.is_array(a):  # static parts (an optimistix jaxpr) are the same in both
            return b
        d = done.reshape(done.shape + (1,) * (a.ndim - 1))
        return jnp.where(d, a, b)

    return jax.tree_util.tree_map(pick, old, new)


def _over_starts(fn, n_starts):
    """`eqx.filter_vmap(fn)` over the starts' leading axis. With one start, `fn` on that
    start itself (the axis taken off and put back): a vmap of size one still batches the
    predicates of the loops inside (selects on every carry), a larger program to trace
    and compile for the same numbers."""
    if n_starts != 1:
        return eqx.filter_vmap(fn)

    def one(*args):
        args = jax.tree_util.tree_map(lambda a: a[0] if eqx.is_array(a) else a, args)
        out = fn(*args)
        return jax.tree_util.tree_map(lambda a: a[None] if eqx.is_array(a) else a, out)

    return one


def _scores(problem: FitProblem, params: Params, val_x0):
    """The validation loss of every start's iterate and the records' x0 it used."""
    mon = problem.validation
    return jax.vmap(lambda p, g: mon.score(problem.model, problem.theta_of(p), g))(
        params.theta, val_x0
    )


def _update_best(best: Best, params, score, val_x0, running, tie, stage, step):
    """Keep the iterate where its score improves on the best; count the others (a start
    that has stopped keeps its count). The current iterate stands for the best one
    (`here`) where it improves on it or ties with it, within `tie` (`Monitor.tie`) of the
    lowest score: a step that a solver rejects leaves the iterate, and its score, as they
    were, and the point the solver stops at is then still the best; and a solver that
    converges past the lowest score by a difference the held-out records cannot resolve
    keeps its solution."""
    better = score < best.score
    lowest = jnp.where(better, score, best.score)
    return Best(
        lowest,
        _freeze(better, params, best.params),
        val_x0,
        # (no finite score yet: nothing to improve on, so no patience spent)
        jnp.where(
            better, 0, best.since + (running & jnp.isfinite(best.score)).astype(best.since.dtype)
        ),
        (score <= lowest + tie(lowest)) | (best.here & ~running),
        score,
        jnp.where(better, jnp.asarray(stage, best.stage.dtype), best.stage),
        jnp.where(better, jnp.asarray(step, best.step.dtype), best.step),
    )


def _got(value) -> str:
    """What a solver's method returned, in words, for its error message."""
    if hasattr(value, "_fields"):  # (a NamedTuple: Params, a solver's state)
        return type(value).__name__
    if isinstance(value, (tuple, list)):
        return f"a {type(value).__name__} of {len(value)}: ({', '.join(map(_got, value))})"
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return f"an array of shape {tuple(value.shape)} and dtype {value.dtype}"
    return type(value).__name__


def _returns(solver, method, ok, out, expected):
    if not ok:
        raise TypeError(
            f"`{type(solver).__name__}.{method}` must return {expected}; got {_got(out)}. "
            "(See `oneshot_jax.AbstractSolver` and the solvers guide's `GradientDescent`.)"
        )
    return out


def _scalar(v, kind="floating") -> bool:
    return hasattr(v, "dtype") and jnp.ndim(v) == 0 and jnp.issubdtype(v.dtype, getattr(jnp, kind))


def _summary(solver, state):
    """`solver.summary(state)`, checked (a solver of one's own): two scalars."""
    out = solver.summary(state)
    ok = isinstance(out, tuple) and len(out) == 2 and all(_scalar(v) for v in out)
    return _returns(
        solver, "summary(state)", ok, out, "(C, gradient norm): a tuple of two float scalars"
    )


def _terminate(solver, problem, params, state):
    """`solver.terminate(...)`, checked: a boolean scalar and a `RESULTS` item."""
    out = solver.terminate(problem, params, state)
    ok = (
        isinstance(out, tuple)
        and len(out) == 2
        and _scalar(out[0], "bool_")
        and getattr(out[1], "_enumeration", None) is RESULTS
    )
    return _returns(
        solver,
        "terminate(problem, params, state)",
        ok,
        out,
        "(done, result): a boolean scalar and a oneshot_jax.RESULTS item (RESULTS.converged, say)",
    )


def _step(solver, problem, params, state):
    """`solver.step(...)`, checked: the next `Params` and a state of the same structure."""
    out = solver.step(problem, params, state)
    ok = (
        isinstance(out, tuple)
        and len(out) == 2
        and isinstance(out[0], Params)
        and jax.tree_util.tree_structure(out[1]) == jax.tree_util.tree_structure(state)
    )
    return _returns(
        solver,
        "step(problem, params, state)",
        ok,
        out,
        "(params, state): the next iterate as `Params` (its `theta` and `x0` as in `params`: "
        "`params._replace(theta=...)`) and a state shaped as `init`'s",
    )


def _shown(done_low, loss):
    """The loss a progress bar shows: the smallest over the starts' `loss` (NaN left out)
    and `done_low` (the final losses of the starts already run in turn)."""
    return jnp.minimum(done_low, jnp.min(jnp.where(jnp.isnan(loss), jnp.inf, loss)))


def iterate(
    solver,
    problem: FitProblem,
    params: Params,
    *,
    history_size,
    meter,
    meter_args,
    best=None,
    stage=0,
):
    """Run `solver` from the S starts `params` (leading axis S) until every start has
    terminated or `solver.max_steps` steps are taken. `best`: the previous solver's
    `Best` (with validation data); `stage`: this solver's place in the sequence."""
    n_starts = params.theta.shape[0]
    mon = problem.validation

    def check(p, s):
        loss, gnorm = _summary(solver, s)
        done, result = _terminate(solver, problem, p, s)
        finite = jnp.isfinite(loss) & jnp.isfinite(gnorm)
        return done | ~finite, RESULTS.where(finite, result, RESULTS.diverged), loss, gnorm

    check_all = _over_starts(check, n_starts)
    state = _over_starts(lambda p: solver.init(problem, p), n_starts)(params)
    # A solver that `primes_in_step` evaluates the start in its first step (step 0 of
    # the loop below, recorded as the start); otherwise it is tested here.
    primes = solver.primes_in_step
    if primes:
        done = jnp.zeros(n_starts, bool)
        result = _over_starts(lambda p, s: _terminate(solver, problem, p, s)[1], n_starts)(
            params, state
        )
    else:
        done, result, loss, gnorm = check_all(params, state)
    hist = None  # (`history_size=0`: no history, nothing of it traced)
    if history_size:
        hist = _history.init(
            history_size, n_starts, params.theta.shape[1], problem.dtype, mon is not None
        )
    score = None
    if mon is not None:
        guess = jnp.broadcast_to(mon.x0, (n_starts, *mon.x0.shape)) if best is None else best.val_x0
        score, val_x0 = _scores(problem, params, guess)
        if best is None:
            best = Best(
                score,
                params,
                val_x0,
                jnp.zeros(n_starts, jnp.int32),
                jnp.ones(n_starts, bool),
                score,
                jnp.full(n_starts, stage, jnp.int32),
                jnp.zeros(n_starts, jnp.int32),
            )
        else:  # the starting point is the last solver's final iterate
            best = _update_best(
                best._replace(here=jnp.zeros_like(best.here)),
                params,
                score,
                val_x0,
                ~done,
                mon.tie,
                stage,
                0,
            )
            best = best._replace(since=jnp.zeros_like(best.since))
    if hist is not None and not primes:
        hist = _history.first(hist, loss, gnorm, params.theta, score)
    dynamic, static = eqx.partition(state, eqx.is_array)
    bar_id, offset, done_low = meter_args
    step_all = _over_starts(lambda p, s: _step(solver, problem, p, s), n_starts)

    def cond(c):
        return jnp.any(~c.done) & (c.step < solver.max_steps)

    def body(c):
        state = eqx.combine(c.state, static)
        new_params, new_state = step_all(c.params, state)
        params = _freeze(c.done, c.params, new_params)
        state = _freeze(c.done, state, new_state)
        step = c.step + 1
        done, result, loss, gnorm = check_all(params, state)
        result = _where(c.done, c.result, result)
        score, best = None, c.best
        if mon is not None:
            score, val_x0 = _scores(problem, params, c.best.val_x0)
            best = _update_best(c.best, params, score, val_x0, ~c.done, mon.tie, stage, step)
            if primes:  # (the start's score is in `best` already)
                best = _where(step == 0, c.best, best)
            if mon.patience is not None:
                patience_out = (best.since >= mon.patience) & ~done
                done = done | patience_out
                result = _where(patience_out & ~c.done, RESULTS.validation, result)
        hist = c.history
        if hist is not None:
            hist = _history.record(hist, step, loss, gnorm, params.theta, score)
        meter.update(bar_id, offset, step, _shown(done_low, loss))
        dynamic, _ = eqx.partition(state, eqx.is_array)
        return _Carry(
            params,
            dynamic,
            step,
            c.num_steps + jnp.where(c.done, 0, 1),
            c.done | done,
            result,
            hist,
            best,
        )

    first = jnp.array(-1 if primes else 0, jnp.int32)  # (the priming step is step 0)
    num_steps = jnp.full(n_starts, first, jnp.int32)
    init = _Carry(params, dynamic, first, num_steps, done, result, hist, best)
    c = jax.lax.while_loop(cond, body, init)
    state = eqx.combine(c.state, static)
    result = _where(c.done, c.result, RESULTS.max_steps_reached)
    final_loss, final_gnorm = _over_starts(lambda s: _summary(solver, s), n_starts)(state)
    if callable(getattr(meter, "finish", None)):  # (optional: `TqdmProgress`)
        meter.finish(bar_id, offset, c.step, _shown(done_low, final_loss))
    measures = _over_starts(solver.measures, n_starts)(state)
    out_params, out_loss, blocks = _over_starts(
        lambda p, s, r: solver.postprocess(problem, p, s, r), n_starts
    )(c.params, state, result)
    # (a least-squares stop at lambda h < 0: its sum of squares is not the loss, which
    # the history's last row gives too)
    final_loss = jnp.where(result == RESULTS.negative_penalty, out_loss, final_loss)
    best = c.best
    solver_result = result
    if mon is not None:
        # The best-scoring iterate replaces the final one where they differ: its loss is
        # evaluated there, and the covariance then takes a fresh Jacobian (no blocks).
        # A tie keeps the point a solver stopped at only where it stopped with a success
        # (a solution, a difference of scores the records cannot resolve); any other stop
        # (its step budget, `patience`) returns the best-scored iterate unless it is
        # that iterate's score exactly (a rejected last step leaves both as they were).
        here = best.here & (succeeded(result) | (best.last <= best.score))
        best = best._replace(here=here & (result != RESULTS.validation))
        moved = ~best.here
        result = _where(moved, RESULTS.validation, result)
        out_params = _freeze(moved, best.params, out_params)
        best_loss = jax.vmap(lambda p: problem.loss(p) + problem.g(p.theta))(best.params)
        out_loss = jnp.where(moved, best_loss, out_loss)
        blocks = None
    return Solution(
        out_params,
        out_loss,
        result,
        c.num_steps,
        c.history,
        final_loss,
        final_gnorm,
        c.params.theta,
        blocks,
        measures,
        best,
        solver_result,
    )


# Whether `fit` takes the starts of a multistart in turn (True) or side by side (False);
# None: in turn on a CPU, side by side on an accelerator, where a batch of starts shares the
# kernel launches of a step (on an H100, `benchmarks/gpu/h100_multistart_*.txt`: faster
# than in turn with LM and Adam at T = 500, slower with GN and on the parallel path at
# T = 2000). Read on the host by `starts_in_turn` at each fit.
STARTS_IN_TURN: bool | None = None


def starts_in_turn() -> bool:
    """Whether a multistart's starts run in turn (`STARTS_IN_TURN`, by default on a CPU)."""
    if STARTS_IN_TURN is not None:
        return bool(STARTS_IN_TURN)
    return jax.default_backend() == "cpu"


def _one_start(params: Params, i) -> Params:
    return jax.tree_util.tree_map(lambda a: a[i][None], params)


def _unstack(sol: Solution) -> Solution:
    """A `Solution` of `lax.scan` over starts (every leaf (S, 1, ...)) as the side-by-side
    one (leaves (S, ...)), but for the history: its rows (size, S, ...) and the steps,
    row count and stride of each start (S, ...), no longer shared."""
    drop = lambda a: a[:, 0]  # noqa: E731
    h = sol.history
    if h is not None:
        rows = lambda a: None if a is None else jnp.moveaxis(a[:, :, 0], 0, 1)  # noqa: E731
        h = h._replace(
            loss=rows(h.loss),
            grad_norm=rows(h.grad_norm),
            validation=rows(h.validation),
            theta=rows(h.theta),
        )
    rest = jax.tree_util.tree_map(drop, sol._replace(history=None))
    return rest._replace(history=h)


def run(
    solvers, problem: FitProblem, params: Params, *, history_size, meter, bar_id, in_turn=False
):
    """The solvers in order, each from where the last stopped; S starts at once (or, with
    `in_turn`, one after another). Returns every stage's `Solution` (the last one holds
    the result)."""
    n_starts = params.theta.shape[0]
    inf = jnp.array(jnp.inf, problem.dtype)
    if in_turn and n_starts > 1:
        total = sum(s.max_steps for s in solvers)

        def one(low, i):
            # `low`: the least final loss of the starts done, for the progress bar.
            stages = _run(
                solvers,
                problem,
                _one_start(params, i),
                history_size=history_size,
                meter=meter,
                bar_id=bar_id,
                offset=i * total,
                done_low=low,
            )
            last = stages[-1].loss
            return jnp.minimum(low, jnp.min(jnp.where(jnp.isnan(last), inf, last))), stages

        _, stages = jax.lax.scan(one, inf, jnp.arange(n_starts, dtype=jnp.int32))
        return [_unstack(s) for s in stages]
    return _run(
        solvers,
        problem,
        params,
        history_size=history_size,
        meter=meter,
        bar_id=bar_id,
        done_low=inf,
    )


def _run(
    solvers, problem: FitProblem, params: Params, *, history_size, meter, bar_id, done_low, offset=0
):
    stages = []
    offset = jnp.asarray(offset, jnp.int32)
    best = None
    for i, solver in enumerate(solvers):
        sol = iterate(
            solver,
            problem,
            params,
            history_size=history_size,
            meter=meter,
            meter_args=(bar_id, offset, done_low),
            best=best,
            stage=i,
        )
        best = sol.best
        stages.append(sol)
        params = sol.params
        offset = offset + solver.max_steps
    return stages
