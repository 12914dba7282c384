"""The initial states alone by least squares, theta fixed: the x0 solve below `fit`.

A `FitProblem` whose free variables are the initial states only (every entry of theta
fixed, `theta_free = ()`), run by the solvers' loop (`oneshot_jax._iterate.run`) as one
compiled call: it minimises the multi-step cost C of eq. (5) over x0, with the x0 columns
of the closed-form sensitivities (the forward twin of eq. (20)) as the Jacobian of the
least-squares solvers. N trajectories are one problem, as in `fit`: their x0 blocks are
independent, and one solver run moves them together. `estimate_x0` (one head, N = 1),
`predict` and the windows' starting states (`oneshot_jax._windows`) use it; the numbers
are those of `fit(..., fixed=True)` on the same data.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._checks import Data, check_cost
from ._covariance import covariance, scale
from ._iterate import run
from ._problem import FitProblem, Params
from ._progress import NoProgress
from ._results import RESULTS, from_index
from ._simulate import simulate_impl
from ._solver_arg import as_solvers

_NO_PROGRESS = NoProgress()


class X0Fit(NamedTuple):
    """What `solve_x0` returns (NumPy arrays, a leading axis of N trajectories).

    - `x0`: the estimated initial states (N, n_x).
    - `loss`: C of eq. (5) at them, over all N trajectories together.
    - `stop_reason`: the `RESULTS` item of the (last) solver.
    - `residuals`: e = zhat - z (N, T, n_z), NaN at masked samples.
    - `covariance`: sigma^2 (J^T J)^+ (N, n_x, n_x) with sigma^2 = SSE / (n_obs - N n_x)
        (inf in the rows and columns of an entry the outputs do not determine, and
        everywhere when n_obs <= N n_x); None when not asked for.
    """

    x0: np.ndarray
    loss: np.ndarray
    stop_reason: RESULTS
    residuals: np.ndarray
    covariance: np.ndarray | None


@eqx.filter_jit
def _solve(solvers, problem: FitProblem, start: Params, with_covariance: bool):
    """The solvers from one start, then the residuals (and the covariance blocks) at the
    solution: one compiled call, its output packed (`_pytree.pack`)."""
    final = run(solvers, problem, start, history_size=2, meter=_NO_PROGRESS, bar_id=0)[-1]
    params = jax.tree_util.tree_map(lambda a: a[0], final.params)
    strategy = getattr(solvers[-1], "strategy", "auto")
    X0 = problem.x0_of(params.x0)
    _, zhat = simulate_impl(
        problem.model, problem.theta_of(params.theta), X0, problem.u, True, strategy
    )
    zs = problem.z
    e = (
        zhat - zs
        if problem.mask is None
        else jnp.where(problem.mask.outputs > 0, zhat - zs, jnp.nan)
    )
    cov = None
    if with_covariance:
        blocks = (
            None if final.blocks is None else jax.tree_util.tree_map(lambda a: a[0], final.blocks)
        )
        cov = covariance(problem, params, strategy, blocks)
    return _pytree.pack((X0, final.loss[0], final.result._value[0], e, cov))


def solve_x0(data: Data, solver=None, *, with_covariance: bool = True) -> X0Fit:
    """Minimise C of eq. (5) over the initial states alone, theta fixed.

    **Arguments:**

    - `data`: checked data (`_checks.check_data`): one trajectory (x0 (n_x,), u (T, n_u),
        z (T, n_z)) or N (a leading axis), with its weight and mask; `data.x0` is the
        starting guess.
    - `solver`: as `fit`'s `solver` (default `GaussNewton()`).
    - `with_covariance`: also the covariance of the estimates.

    **Returns:**

    An `X0Fit` with a leading axis of trajectories (N = 1 for one).
    """
    solvers = as_solvers("gauss_newton" if solver is None else solver)
    batched = data.batched
    X0, U, Z = (
        np.asarray(a) if batched else np.asarray(a)[None] for a in (data.x0, data.u, data.z)
    )
    flat0, unravel = _pytree.ravel(data.theta)
    mask = None
    if data.mask is not None:
        mask = jax.tree_util.tree_map(
            lambda a: np.asarray(a) if batched else np.asarray(a)[None], data.mask
        )
    problem = _pytree.build(
        FitProblem,
        model=data.model,
        cost=check_cost(data, None, 1.0),
        u=U,
        z=Z,
        theta_base=flat0,
        theta_free=(),
        unravel=unravel,
        x0_base=X0,
        x0_free=tuple(range(X0.shape[1])),
        project=None,
        lower=None,
        upper=None,
        regulariser=None,
        mask=mask,
    )
    start = Params(np.zeros((1, 0), flat0.dtype), X0[None])
    buffers, layout = _solve(solvers, problem, start, with_covariance)
    x0, loss, result, e, cov = _pytree.unpack(buffers, layout)
    x0_cov = None
    if cov is not None:
        x0_cov = scale(cov, int(np.count_nonzero(np.isfinite(e)))).x0
    return X0Fit(x0, loss, from_index(int(result)), e, x0_cov)
