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

import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._checks import Data, check_cost
from ._cost import weigh
from ._covariance import covariance, scale
from ._iterate import run
from ._jit import jit
from ._linalg import identifiable
from ._problem import FitProblem, Params
from ._progress import NoProgress
from ._results import RESULTS, from_index
from ._simulate import outputs, rollout, simulate_impl
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
    - `identifiable`: with a `record`, per x0 entry whether the outputs determine it
        (`identifiable` of J^T J at the estimate, as `identifiable_x0`); else None.
    - `record`: with a `record`, its states (T, n_x) and outputs (T, n_z) simulated from
        the estimate; else None.
    """

    x0: np.ndarray
    loss: np.ndarray
    stop_reason: RESULTS
    residuals: np.ndarray
    covariance: np.ndarray | None
    identifiable: np.ndarray | None = None
    record: tuple | None = None


def identifiable_x0(model, theta, x0, u, sqrt_q, free=None):
    """Per x0 entry, whether it is identifiable from Q^{1/2} z[0..n-1]: `identifiable` of
    J^T J, J = Q^{1/2} d z[0..n-1] / d x0 (n n_z, n_x) by forward mode (traced).

    **Arguments:** `model`, `theta`; `x0` (n_x,); `u` (n, n_u) the head's inputs;
    `sqrt_q` Q^{1/2} (`Cost.sqrt_weight`) or None; `free`: a tuple of the estimated
    entries (J's columns of those alone; the others, held, count identifiable), or None
    (all).

    **Returns:** (n_x,) booleans.
    """

    def weighted_outputs(x0):
        return weigh(outputs(model, theta, rollout(model, theta, x0, u), u), sqrt_q).reshape(-1)

    J = jax.jacfwd(weighted_outputs)(x0)
    if free is None:
        return identifiable(J.T @ J)
    J = J[:, np.asarray(free, int)]
    return jnp.ones(x0.shape, bool).at[np.asarray(free, int)].set(identifiable(J.T @ J))


@jit
def _solve(solvers, problem: FitProblem, start: Params, with_covariance: bool, record=None):
    """The solvers from one start, then the residuals (and the covariance blocks) at the
    solution, and with a `record`'s inputs (one trajectory) the identifiability of x0 and
    the record simulated from it: one compiled call, its output packed (`_pytree.pack`)."""
    final = run(solvers, problem, start, history_size=0, meter=_NO_PROGRESS, bar_id=0)[-1]
    params = jax.tree_util.tree_map(lambda a: a[0], final.params)
    strategy = getattr(solvers[-1], "strategy", "auto")
    X0 = problem.x0_of(params.x0)
    theta = problem.theta_of(params.theta)
    if record is None:
        _, zhat = simulate_impl(problem.model, theta, X0, problem.u, True, strategy)
    else:  # the record starts where the data start: its head is the data's simulation
        sim = simulate_impl(problem.model, theta, X0[0], record, False)
        zhat = sim[1][None, : problem.u.shape[1]]
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
        cov = scale(covariance(problem, params, strategy, blocks), e, problem.cost)
    extra = None
    if record is not None:
        if cov is None:
            sqrt_q = problem.cost.sqrt_weight()
            ok = identifiable_x0(problem.model, theta, X0[0], problem.u[0], sqrt_q)
        else:  # `identifiable` of the same J^T J (the residuals' x0 block, weighted)
            ok = cov.x0_identifiable[0]
        extra = (ok, sim)
    return _pytree.pack((X0, final.loss[0], final.result._value[0], e, cov, extra))


def solve_x0(
    data: Data,
    solver=None,
    *,
    with_covariance: bool = True,
    record=None,
    estimate=None,
    bounds=None,
) -> X0Fit:
    """Minimise C of eq. (5) over the initial states alone, theta fixed.

    **Arguments:**

    - `data`: checked data (`_checks.check_data`): one trajectory (x0 (n_x,), u (T, n_u),
        z (T, n_z)) or N (a leading axis), with its weight and mask; `data.x0` is the
        starting guess.
    - `solver`: as `fit`'s `solver` (default `GaussNewton()`).
    - `with_covariance`: also the covariance of the estimates.
    - `record`: for one trajectory, the inputs (T, n_u) of a whole record that starts
        where the data start (checked as `data.u` is): the identifiability of x0
        (`identifiable_x0`) and the record simulated from the estimate come from the same
        compiled call (`predict`).
    - `estimate`: an (n_x,) boolean mask of the entries to estimate; the others keep
        their value in `data.x0` (zero variance, counted identifiable). Default: all.
    - `bounds`: `(lower, upper)` (N, n_x) bounds on x0 (`_checks.check_x0_bounds`), or
        None; `data.x0` lies in them.

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
    free = tuple(range(X0.shape[1]) if estimate is None else np.flatnonzero(estimate).tolist())
    lower, upper = (None, None) if bounds is None else (b[:, list(free)] for b in bounds)
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
        x0_free=free,
        project=None,
        lower=None,
        upper=None,
        regulariser=None,
        mask=mask,
        x0_lower=lower,
        x0_upper=upper,
    )
    start = Params(np.zeros((1, 0), flat0.dtype), problem.split(flat0, X0).x0[None])
    buffers, layout = _solve(solvers, problem, start, with_covariance, record)
    x0, loss, result, e, cov, extra = _pytree.unpack(buffers, layout)
    x0_cov = None if cov is None else np.asarray(cov.x0)
    ok, sim = (None, None) if extra is None else extra
    if estimate is not None:  # the free entries' blocks, into (n_x, n_x): held ones known
        free = np.flatnonzero(estimate)
        if x0_cov is not None:
            full = np.zeros((x0_cov.shape[0], X0.shape[1], X0.shape[1]), x0_cov.dtype)
            full[:, free[:, None], free[None, :]] = x0_cov
            x0_cov = full
        if ok is not None:
            held = np.ones(X0.shape[1], bool)
            held[free] = np.asarray(ok)
            ok = held
    return X0Fit(x0, loss, from_index(int(result)), e, x0_cov, ok, sim)
