"""The one loop every solver runs in, solver sequences and multistart.

`iterate` runs one solver from one starting point as a `lax.while_loop` (see
`oneshot_jax._solver.base` for the interface), recording a bounded history and updating
the progress bar. `run` chains a sequence of solvers, each starting where the last
stopped, and is what `fit` vmaps over the starting points and compiles as one call.
"""

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _history
from ._problem import FitProblem, Params
from ._results import RESULTS


class Solution(NamedTuple):
    """What one solver returns from one start."""

    params: Params
    loss: jax.Array
    result: RESULTS
    num_steps: jax.Array
    history: _history.History
    blocks: Any  # normal-equation blocks for the covariance, or None


class _Carry(NamedTuple):
    params: Params
    state: Any  # the dynamic (array) part of the solver state
    step: jax.Array
    done: jax.Array
    result: RESULTS
    history: _history.History


def _check_state(solver, problem, params, state):
    """The solver's verdict, plus non-finite values, which always stop the loop."""
    loss, gnorm = solver.summary(state)
    done, result = solver.terminate(problem, params, state)
    finite = jnp.isfinite(loss)
    return done | ~finite, RESULTS.where(finite, result, RESULTS.diverged), loss, gnorm


def iterate(solver, problem: FitProblem, params: Params, *, history_size, meter, meter_args):
    """Run `solver` from `params` until it terminates or takes `solver.max_steps` steps."""
    state = solver.init(problem, params)
    done, result, loss, gnorm = _check_state(solver, problem, params, state)
    hist = _history.init(history_size, params.theta.shape[0], problem.dtype)
    hist = _history.record(hist, jnp.array(0, jnp.int32), loss, gnorm, params.theta)
    dynamic, static = eqx.partition(state, eqx.is_array)
    bar_id, offset = meter_args

    def cond(c):
        return ~c.done & (c.step < solver.max_steps)

    def body(c):
        state = eqx.combine(c.state, static)
        params, state = solver.step(problem, c.params, state)
        step = c.step + 1
        done, result, loss, gnorm = _check_state(solver, problem, params, state)
        hist = _history.record(c.history, step, loss, gnorm, params.theta)
        meter.update(bar_id, offset, step, loss)
        dynamic, _ = eqx.partition(state, eqx.is_array)
        return _Carry(params, dynamic, step, done, result, hist)

    init = _Carry(params, dynamic, jnp.array(0, jnp.int32), done, result, hist)
    c = jax.lax.while_loop(cond, body, init)
    state = eqx.combine(c.state, static)
    result = RESULTS.where(c.done, c.result, RESULTS.max_steps_reached)
    loss, gnorm = solver.summary(state)
    hist = _history.finish(c.history, c.step, loss, gnorm, c.params.theta)
    params, loss, blocks = solver.postprocess(problem, c.params, state, result)
    return Solution(params, loss, result, c.step, hist, blocks)


def run(solvers, problem: FitProblem, params: Params, *, history_size, meter, bar_id):
    """The solvers in order, each from where the last stopped. Returns the last solver's
    `Solution` and the list of every stage's `Solution` (for their histories)."""
    stages = []
    offset = jnp.array(0, jnp.int32)
    for solver in solvers:
        sol = iterate(
            solver,
            problem,
            params,
            history_size=history_size,
            meter=meter,
            meter_args=(bar_id, offset),
        )
        stages.append(sol)
        params = sol.params
        offset = offset + solver.max_steps
    return stages
