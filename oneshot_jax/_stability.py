"""How close a `Model.from_ode` model runs to its explicit integrator's stability limit.

An explicit integrator (`ode_step`: RK4 or Euler, h = dt / substeps) is stable on a mode
of the right-hand side's Jacobian only while lambda h lies in its stability region. A fit
knows nothing of that region: it can move a stiff mode (a friction, a fast pole) out to
where the discrete step f of eq. (1) is no longer the ODE's flow, and the estimates then
depend on `substeps`. `check_stability` evaluates the Jacobian of the right-hand side at
a few states of the fitted trajectory (eq. 7) and compares max |lambda| h with the
integrator's limit; `fit` calls it after every fit of such a model.
"""

import functools
import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from . import _pytree
from ._checks import check_data
from ._jit import jit
from ._model import _ODEStep
from ._simulate import simulate_impl

# The largest |lambda| h taken as safe. RK4's stability region reaches 2.785 on the
# negative real axis and 2.828 on the imaginary axis, and is narrower in between (about
# 2.6 at 135 degrees): 2.5 leaves a margin in every direction. Explicit Euler's region is
# the disc |1 + lambda h| <= 1, which reaches 2 on the negative real axis (and contains
# no point of the imaginary axis: an undamped mode grows under Euler at any h).
LIMITS = {"rk4": 2.5, "euler": 2.0}

# The states the Jacobian is evaluated at: this many, evenly spaced over all samples of
# all trajectories (a few small Jacobians: cheap next to the fit).
POINTS = 32


class Stability(NamedTuple):
    """The largest scaled eigenvalue of a `Model.from_ode` model along a trajectory.

    **Fields:**

    - `value`: max |lambda| h over the states checked, lambda an eigenvalue of the
        Jacobian d rhs / d x, h = dt / substeps.
    - `limit`: the integrator's limit (2.5 for RK4, 2 for Euler).
    - `eigenvalue`: the lambda of `value`.
    - `sample`: where it was found: the index of its state in the trajectories
        flattened (trajectory i, sample k: i T + k).
    - `method`, `substeps`, `dt`: the model's integrator.
    """

    value: float
    limit: float
    eigenvalue: complex
    sample: int
    method: str
    substeps: int
    dt: float

    @property
    def near_limit(self) -> bool:
        """Whether `value` exceeds `limit`."""
        return bool(self.value > self.limit)


def rhs_of(model, data):
    """The right-hand side of a `Model.from_ode` model as the checked data's model sees
    theta (its trainable part, the static part bound in); None for another model."""
    step = model.step
    if not isinstance(step, _ODEStep):
        return None
    bound = data.model.step
    return _pytree.Bound(step.rhs, bound.static) if isinstance(bound, _pytree.Bound) else step.rhs


def sample_points(data, points: int = POINTS) -> np.ndarray | None:
    """The flattened indices (trajectory i, sample k: i T + k) of `points` states evenly
    spaced over the valid samples of the checked data (not the padding of ragged
    trajectories); None where there is none."""
    if data.mask is None:
        return _evenly(math.prod(np.shape(data.u)[:-1]), points)
    valid = np.flatnonzero(np.asarray(data.mask.samples).reshape(-1) > 0)
    if valid.size == 0:
        return None
    return valid[_evenly(valid.size, points)]


@functools.lru_cache(maxsize=64)
def _evenly(n: int, points: int) -> np.ndarray:
    """`points` indices evenly spaced over range(n) (all of them when n <= points)."""
    idx = np.unique(np.linspace(0, n - 1, min(points, n)).astype(int))
    idx.setflags(write=False)
    return idx


def jacobians_at(rhs, theta, xs, u, idx):
    """The states of a trajectory xs (..., T, n_x) at the flattened indices `idx`, and
    d rhs / d x there with their inputs u (..., T, n_u) (forward mode: the state is
    small); traced."""
    xs = xs.reshape(-1, xs.shape[-1])[idx]
    us = u.reshape(-1, u.shape[-1])[idx]
    return xs, jax.vmap(lambda x, u: jax.jacfwd(rhs)(x, u, theta))(xs, us)


def row_bound(xs, J):
    """max over the finite states of ||J||_inf (the largest row sum of |J|, a bound on
    every eigenvalue's modulus); -inf where no state is finite. Traced, so that `fit`
    brings one number to the host (`warn_after_fit`)."""
    finite = jnp.all(jnp.isfinite(xs), axis=1) & jnp.all(jnp.isfinite(J), axis=(1, 2))
    rows = jnp.max(jnp.sum(jnp.abs(J), axis=2), axis=1)
    return jnp.max(jnp.where(finite, rows, -jnp.inf), initial=-jnp.inf)


@jit
def _jacobians(model, params, x0, u, batched, rhs, idx):
    """The states of eq. (7) and d rhs / d x at the flattened states `idx`, in one
    compiled call."""
    xs, _ = simulate_impl(model, params, x0, u, batched)
    return jacobians_at(rhs, params, xs, u, idx)


def report(step, idx, xs, J) -> Stability | None:
    """The `Stability` of the Jacobians `J` at the states `xs` (flattened indices `idx`)
    of a `Model.from_ode` model's `step`, from their eigenvalues (on the host); None
    where no state is finite."""
    xs, J = np.asarray(xs), np.asarray(J)
    finite = np.all(np.isfinite(xs), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
    if not np.any(finite):
        return None
    eig = np.linalg.eigvals(J[finite])
    h = step.dt / step.substeps
    i, j = np.unravel_index(np.argmax(np.abs(eig)), eig.shape)
    return Stability(
        value=float(np.abs(eig[i, j]) * h),
        limit=LIMITS[step.method],
        eigenvalue=complex(eig[i, j]),
        sample=int(idx[finite][i]),
        method=step.method,
        substeps=step.substeps,
        dt=step.dt,
    )


def warn_after_fit(step, idx, xs, J, bound, stacklevel: int) -> None:
    """`fit`'s warning from the Jacobians `J` at the fitted states `xs` (`jacobians_at`)
    and their `row_bound`. Where max |lambda| h is within the limit by that bound times
    h, no eigenvalue is computed."""
    if not float(bound) * step.dt / step.substeps > LIMITS[step.method]:
        return  # (within the limit, or no finite state: -inf)
    warn_if_near_limit(report(step, idx, xs, J), stacklevel=stacklevel + 1)


def stability(model, theta, x0, u, *, points: int = POINTS) -> Stability | None:
    """`check_stability` without its checks of the arguments and without the warning;
    None for a model not built by `Model.from_ode` or without a finite state."""
    if not isinstance(model.step, _ODEStep):
        return None
    data = check_data(model, theta, x0, u)
    idx = sample_points(data, points)
    if idx is None:
        return None
    xs, J = _jacobians(
        data.model, data.theta, data.x0, data.u, data.batched, rhs_of(model, data), idx
    )
    return report(model.step, idx, xs, J)


def warn_if_near_limit(report: Stability | None, stacklevel: int) -> None:
    """The warning of `check_stability`, where `report` exceeds its limit."""
    if report is None or not report.near_limit:
        return
    lam = report.eigenvalue
    need = int(np.ceil(report.value * report.substeps / report.limit))
    warnings.warn(
        f"the fitted model runs near its integrator's stability limit: a Jacobian "
        f"eigenvalue of the right-hand side, lambda = {lam.real:.4g}{lam.imag:+.4g}j, gives "
        f"|lambda| h = {report.value:.3g} with h = dt / substeps = {report.dt:g} / "
        f"{report.substeps} ({report.method.upper()}: stable up to about {report.limit:g}). "
        "The estimates may depend on the discretisation rather than on the ODE: refit with "
        f"more substeps (`Model.from_ode(..., substeps={max(need, 2 * report.substeps)})` "
        "or more), and compare.",
        RuntimeWarning,
        stacklevel=stacklevel + 1,
    )


def check_stability(
    model,
    theta: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    *,
    points: int = POINTS,
) -> Stability | None:
    """Check that a `Model.from_ode` model runs inside its integrator's stability region.

    Simulates the model (eq. 7), evaluates the Jacobian of the right-hand side d rhs / d x
    at `points` states evenly spaced along the trajectory (with their inputs) and returns
    the largest |lambda| h, h = dt / substeps, over their eigenvalues lambda. Above about
    2.5 for RK4 (its stability region reaches 2.785 on the negative real axis, 2.828 on
    the imaginary one) or 2 for Euler it warns (RuntimeWarning), naming the eigenvalue
    and how many substeps would bring it back inside. `fit` runs this check on the
    fitted theta and x0 after every fit of a `Model.from_ode` model.

    **Arguments:**

    - `model`: a `Model` built by `Model.from_ode` (for any other model the check
        returns None: its step is not a known integrator).
    - `theta`, `x0`, `u`: as for `oneshot_jax.simulate`.
    - `points`: how many states to evaluate the Jacobian at.

    **Returns:**

    A `Stability` (`value`, `limit`, `eigenvalue`, ...), or None for a model not built by
    `Model.from_ode` or one whose trajectory has no finite state.
    """
    if isinstance(points, bool) or int(points) != points or points < 1:
        raise ValueError(f"`points` must be a positive integer, got {points!r}.")
    report = stability(model, theta, x0, u, points=int(points))
    warn_if_near_limit(report, stacklevel=2)
    return report
