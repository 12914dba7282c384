"""`fit`: estimate theta and x0 by minimising the multi-step loss (Algorithm 1 and friends)."""

import dataclasses
import functools
import time
import warnings
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from . import metrics as _metrics
from ._checks import as_theta, check_data, check_penalty, check_strategy
from ._model import _identity_observe
from ._simulate import _simulate, check_penalty_output
from ._solvers import (
    Problem,
    StopReason,
    adam,
    covariance_blocks,
    run_first_order,
    run_least_squares,
)
from .constraints import combine

_LSQ = ("gauss_newton", "levenberg_marquardt")
_SOLVER_NAMES = ("adam", *_LSQ)


@dataclasses.dataclass(frozen=True)
class FitResult:
    """What `fit` returns (cf. scipy's OptimizeResult and MATLAB's idnlgrey reports).

    **Fields:**

    - `theta`: estimated parameters, same pytree as `theta0`.
    - `x0`: estimated initial state(s), shape (n_x,) or (N, n_x).
    - `loss`: final C (eq. 5/21).
    - `stop_reason`: a `StopReason`; `stop_reason.message` says why, `success` if converged.
    - `epochs`: iterations run; `wall_time`: seconds of the solve with the covariance and
        metrics (one compiled call; compilation included), without the input checks.
    - `history`: dict with `loss` and `grad_norm` per epoch and `theta`, the iterates
        (theta's pytree with a leading epoch axis); optimistix solvers record only the
        final point.
    - `residuals`: e = zhat - z, shape of `z`.
    - `names`: a name per free parameter (`"k"`, `"I[2]"`).
    - `covariance`: sigma^2 (J^T J)^{-1} of the free parameters of theta (J the
        data-residual Jacobian in the weighted error, sigma^2 = SSE / (n_obs - n_free)).
        The least-squares solvers take J from their last linearisation, at the returned
        point or one converged step (relative size <= rtol) before it.
    - `std`, `ci95`: standard errors and 95% intervals (value -+ 1.96 std) shaped like
        theta; fixed entries have std 0. `x0_std`: standard errors of x0 (0 where fixed).
    - `metrics`: RMSE, NRMSE, FIT%, R^2 per output and AIC on the fitted data.
    - `starts`: for a multi-start fit, the per-start theta (leading axis), loss and stop
        codes; `best` is the index of the returned start.
    """

    theta: Any
    x0: jax.Array
    loss: float
    stop_reason: StopReason
    epochs: int
    wall_time: float
    history: dict
    residuals: jax.Array
    names: tuple
    covariance: np.ndarray
    std: Any
    ci95: tuple
    x0_std: np.ndarray
    metrics: dict
    starts: dict | None = None
    best: int = 0

    @property
    def success(self) -> bool:
        return self.stop_reason.success

    def __str__(self):
        flat, _ = ravel_pytree(self.theta)
        std, _ = ravel_pytree(self.std)
        rows = [f"oneshot_jax fit: {self.stop_reason.name} ({self.stop_reason.message})"]
        rows.append(
            f"  loss {self.loss:.6e} after {self.epochs} epochs in {self.wall_time:.3g} s "
            "(wall, compilation included)"
        )
        rows.append(f"  {'parameter':<14}{'value':>14}{'std':>12}{'95% interval':>30}")
        for name, v, s in zip(_all_names(self.theta), np.asarray(flat), np.asarray(std)):
            ci = f"[{v - 1.96 * s:.6g}, {v + 1.96 * s:.6g}]" if s > 0 else "(fixed)"
            rows.append(f"  {name:<14}{v:>14.6g}{s:>12.3g}{ci:>30}")
        fitp = ", ".join(f"{f:.2f}" for f in np.atleast_1d(self.metrics["fit_percent"]))
        rmse = ", ".join(f"{f:.4g}" for f in np.atleast_1d(self.metrics["rmse"]))
        rows.append(f"  FIT% [{fitp}]  RMSE [{rmse}]  AIC {self.metrics['aic']:.4g}")
        return "\n".join(rows)

    __repr__ = __str__


def _all_names(theta):
    """One name per scalar of theta: dict keys (with [i] for array entries) or leaf paths."""
    names = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(theta)[0]:
        base = (
            "".join(
                str(getattr(p, "key", getattr(p, "idx", getattr(p, "name", p))))
                if i == 0
                else f".{getattr(p, 'key', getattr(p, 'idx', getattr(p, 'name', p)))}"
                for i, p in enumerate(path)
            )
            or "theta"
        )
        size = int(np.size(leaf))
        if np.ndim(leaf) == 0:
            names.append(base)
        else:
            names.extend(
                f"{base}[{', '.join(map(str, ix))}]" if np.ndim(leaf) > 1 else f"{base}[{ix[0]}]"
                for ix in np.ndindex(np.shape(leaf))
            )
        assert len(names) >= size
    return tuple(names)


def _check_solver(solver):
    if isinstance(solver, str):
        if solver not in _SOLVER_NAMES:
            raise ValueError(
                f"unknown `solver` {solver!r}; valid names are {', '.join(_SOLVER_NAMES)}, or "
                "pass an optax.GradientTransformation or an optimistix least-squares solver."
            )
        return solver
    if isinstance(solver, optx.AbstractLeastSquaresSolver):
        return solver
    if hasattr(solver, "init") and hasattr(solver, "update"):
        return solver
    raise ValueError(
        f"`solver` must be one of {', '.join(_SOLVER_NAMES)}, an optax.GradientTransformation "
        f"or an optimistix least-squares solver, got {solver!r}."
    )


def _fixed_mask(fixed, theta):
    """Flat boolean mask of fixed entries from a pytree of bools shaped like theta."""
    flat, _ = ravel_pytree(theta)
    if fixed is None:
        return np.zeros(flat.shape, bool)
    if jax.tree_util.tree_structure(fixed) != jax.tree_util.tree_structure(theta):
        raise ValueError(
            "`fixed` must be a pytree of booleans with the structure of theta0 "
            f"({jax.tree_util.tree_structure(theta)}), got {jax.tree_util.tree_structure(fixed)}."
        )
    parts = []
    for f, t in zip(jax.tree_util.tree_leaves(fixed), jax.tree_util.tree_leaves(theta)):
        f = np.asarray(f)
        if f.dtype != bool:
            raise ValueError(f"`fixed` entries must be booleans, got dtype {f.dtype}.")
        try:
            parts.append(np.broadcast_to(f, np.shape(t)).reshape(-1))
        except ValueError as err:
            raise ValueError(
                f"`fixed` entry of shape {f.shape} does not fit a parameter of shape {np.shape(t)}."
            ) from err
    return np.concatenate(parts) if parts else np.zeros(0, bool)


def _x0_mask(estimate_x0, n_x):
    est = np.asarray(estimate_x0)
    if est.dtype != bool or est.shape not in ((), (n_x,)):
        raise ValueError(
            f"`estimate_x0` must be a bool or a boolean mask of shape ({n_x},), "
            f"got {estimate_x0!r}."
        )
    return np.broadcast_to(est, (n_x,)).copy()


def _sqrt_weight(weight):
    if weight is None:
        return None
    if weight.ndim == 1:
        return jnp.sqrt(weight)
    vals, vecs = jnp.linalg.eigh(weight)
    return (vecs * jnp.sqrt(jnp.maximum(vals, 0.0))) @ vecs.T


def _flat_host(tree):
    """`ravel_pytree(tree)[0]` as a NumPy array, without a JAX call."""
    return np.concatenate([np.ravel(np.asarray(a)) for a in jax.tree_util.tree_leaves(tree)])


def _windows(model, theta, x0, u, z, window):
    """Cut one record into consecutive windows, each with an initial state of its own:
    taken from z where the model observes its whole state (z = x), else simulated."""
    T = u.shape[0]
    if int(window) != window or window < 1:
        raise ValueError(f"`window` must be a positive integer, got {window!r}.")
    if window > T:
        raise ValueError(f"`window` ({window}) is longer than the record (T = {T}).")
    N = T // window
    if N * window != T:
        warnings.warn(
            f"the last {T - N * window} samples do not fill a window and are dropped.", stacklevel=3
        )
    u_w = u[: N * window].reshape(N, window, -1)
    z_w = z[: N * window].reshape(N, window, -1)
    if model.observe is _identity_observe:
        x0_w = jnp.asarray(z_w[:, 0, :]).astype(x0.dtype).at[0].set(x0)
    else:
        xs, _ = _simulate(model, theta, x0, u[: N * window], False)
        x0_w = xs[::window]
    return x0_w, u_w, z_w


def fit(
    model,
    u,
    z,
    theta0,
    x0,
    *,
    solver="adam",
    max_epochs=None,
    tol_loss=0.0,
    tol_grad=0.0,
    rtol=1e-10,
    weight=None,
    penalty=None,
    penalty_weight=1.0,
    constraints=None,
    fixed=None,
    estimate_x0=True,
    window=None,
    multistart=False,
    strategy="auto",
) -> FitResult:
    """Estimate theta and x0 by minimising the multi-step cost C of eq. (5)/(21).

    **Arguments:**

    - `model`: a `Model`.
    - `u`, `z`: inputs (T, n_u) and measured outputs (T, n_z), or (N, T, .) for N
        trajectories sharing theta, each with its own x0.
    - `theta0`: initial parameter pytree. With `multistart=True` every leaf has a leading
        axis of starts, run in parallel (vmap); the best final loss is returned.
    - `x0`: initial state guess (n_x,) or (N, n_x) (with `multistart`, optionally a leading
        axis of starts too).
    - `solver`: `"adam"` (Algorithm 1 with `oneshot_jax.adam()`), any
        `optax.GradientTransformation` (it sees the dict `{"theta": p, "x0": q}` of free
        entries), `"gauss_newton"` or `"levenberg_marquardt"` (structured solvers on the
        closed-form Jacobian, exact box constraints), or an optimistix least-squares solver
        instance (`optx.GaussNewton`, `LevenbergMarquardt`, `Dogleg`, ...) fed the
        closed-form Jacobian through `jax.custom_jvp`.
    - `max_epochs`: E_max (default 5000 for first-order solvers, 100 otherwise).
    - `tol_loss`, `tol_grad`: stop when C < tol_loss (epsilon) or ||grad C|| < tol_grad
        (delta) (Algorithm 1 line 3). `rtol`: least-squares solvers stop when an accepted
        step changes every free parameter by less than rtol relative.
    - `weight`, `penalty`, `penalty_weight`: as for `loss`. Least-squares solvers add the
        penalty as residuals sqrt(penalty_weight h / T), so h must be >= 0 there.
    - `constraints`: a projection from `oneshot_jax.constraints` (or a list), on theta.
    - `fixed`: pytree of booleans shaped like theta0 (per leaf or per element): True
        entries keep their initial value and are removed from the variables.
    - `estimate_x0`: False keeps x0 fixed; a (n_x,) boolean mask estimates some entries.
    - `window`: cut one record into windows of this many samples, each with its own x0.
    - `strategy`: how the per-step Jacobians enter: for first-order solvers the gradient
        strategy of `value_and_grad`; for `"gauss_newton"`/`"levenberg_marquardt"` the
        sensitivity recursion, `"jacobian"` forming J^{x/x}, J^{x/theta} after the forward
        pass (Remark 1) or `"vjp"` pushing the Jacobian's columns through the step as JVPs
        inside the scan (matrix-free); `"auto"` forms them for small states and batches.

    **Returns:**

    A `FitResult`.
    """
    solver = _check_solver(solver)
    if max_epochs is None:
        max_epochs = (
            100
            if (isinstance(solver, str) and solver in _LSQ)
            or isinstance(solver, optx.AbstractLeastSquaresSolver)
            else 5000
        )
    if int(max_epochs) != max_epochs or max_epochs < 0:
        raise ValueError(f"`max_epochs` must be a non-negative integer, got {max_epochs!r}.")
    max_epochs = int(max_epochs)
    strategy = check_strategy(strategy)
    penalty, penalty_weight = check_penalty(penalty, penalty_weight)

    # Starting points: theta0 (S, ...) and x0 (S, ...) with multistart, else one start.
    theta0 = as_theta(theta0)
    if multistart:
        sizes = {
            jnp.shape(leaf)[0] if jnp.ndim(leaf) else None
            for leaf in jax.tree_util.tree_leaves(theta0)
        }
        if len(sizes) != 1 or None in sizes:
            raise ValueError(
                "with `multistart=True` every leaf of `theta0` needs the same leading axis "
                "of starts."
            )
        n_starts = sizes.pop()
        theta_first = jax.tree_util.tree_map(lambda a: a[0], theta0)
    else:
        n_starts, theta_first = None, theta0

    # The data stay as given until `check_data` converts them (once).
    u_arr, z_arr, x0_arr = u, z, x0
    x0_starts = None
    data_ndim_x0 = 2 if np.ndim(u_arr) == 3 else 1
    if multistart and np.ndim(x0_arr) == data_ndim_x0 + 1:
        x0_starts = jnp.asarray(x0_arr)
        x0_arr = x0_starts[0]
    if window is not None:
        if np.ndim(u_arr) != 2:
            raise ValueError(
                f"`window` needs one record: `u` of shape (T, n_u), got {np.shape(u_arr)}."
            )
        data = check_data(model, theta_first, x0_arr, u_arr, z_arr, weight)
        x0_w, u_w, z_w = _windows(model, data.theta, data.x0, data.u, data.z, window)
        data = check_data(model, theta_first, x0_w, u_w, z_w, weight)
        if x0_starts is not None:
            raise ValueError("`window` with per-start x0 is not supported: give one x0.")
    else:
        data = check_data(model, theta_first, x0_arr, u_arr, z_arr, weight)
    check_penalty_output(model, penalty, data)
    batched = data.batched
    # Host-side (NumPy) views with the trajectory axis: no eager JAX call per array; the
    # compiled call below takes them as they are.
    X0, U, Z = (np.asarray(a) if batched else np.asarray(a)[None] for a in data[1:4])
    n_x = X0.shape[1]

    flat0, unravel = ravel_pytree(data.theta)
    fixed_mask = _fixed_mask(fixed, data.theta)
    theta_free = np.flatnonzero(~fixed_mask)
    x0_free = np.flatnonzero(_x0_mask(estimate_x0, n_x))

    proj = combine(constraints)
    lower = upper = None
    if proj is not None and proj.bounds is not None:
        lo, hi = proj.bounds(data.theta)
        # Host-side (numpy) indexing: an eager JAX gather costs a dispatch per call.
        lower = _flat_host(lo)[theta_free]
        upper = _flat_host(hi)[theta_free]

    problem = Problem(
        model=model,
        u=U,
        z=Z,
        weight=data.weight,
        sqrt_q=_sqrt_weight(data.weight),
        penalty=penalty,
        penalty_weight=np.asarray(penalty_weight, X0.dtype),
        theta_base=flat0,
        theta_free=tuple(int(i) for i in theta_free),
        unravel=unravel,
        x0_base=X0,
        x0_free=tuple(int(i) for i in x0_free),
        project=None if proj is None else (proj.project if proj.bounds is None else None),
        lower=lower,
        upper=upper,
        strategy=strategy,
    )

    # Every start as free-variable arrays (built on the host), projected onto the set.
    if multistart:
        starts_flat = np.asarray(jax.vmap(lambda t: ravel_pytree(t)[0])(theta0))
        if x0_starts is not None:
            X0s = np.asarray(x0_starts if batched else x0_starts[:, None])
        else:
            X0s = np.broadcast_to(np.asarray(X0), (n_starts, *X0.shape))
    else:
        starts_flat, X0s = np.asarray(flat0)[None], np.asarray(X0)[None]
    pt0 = starts_flat[:, theta_free]
    px0 = X0s[:, :, x0_free]
    if len(theta_free) == 0 and len(x0_free) == 0:
        raise ValueError("nothing to estimate: every parameter is fixed and estimate_x0 is False.")

    t0 = time.perf_counter()
    if isinstance(solver, optx.AbstractLeastSquaresSolver):
        moved, pt0 = _project_starts_jit(problem, pt0)
        outs = [
            _run_optimistix(problem, solver, pt0[s], px0[s], max_epochs, rtol, proj)
            for s in range(pt0.shape[0])
        ]
        pt, px, C, code, epochs, hist = (jnp.stack(a) for a in zip(*outs))
        best = int(np.argmin(np.where(np.isfinite(np.asarray(C)), np.asarray(C), np.inf)))
        post = _post_jit(problem, pt[best], px[best])
    else:
        run = _compiled_runner(solver, max_epochs)
        moved, (pt, px, C, code, epochs, hist), best, post = run(
            problem, pt0, px0, tol_loss, tol_grad, rtol
        )
    jax.block_until_ready(post)
    wall = time.perf_counter() - t0
    if bool(moved):
        warnings.warn(
            "theta0 lies outside the constraint set; it was projected onto it.", stacklevel=2
        )

    pt, px, C, code, epochs, hist = (np.asarray(a) for a in (pt, px, C, code, epochs, hist))
    best = int(best)
    return _result(
        problem,
        data,
        batched,
        post,
        float(C[best]),
        int(code[best]),
        int(epochs[best]),
        hist[best],
        wall,
        starts=None if not multistart else _starts(problem, pt, C, code),
        best=best,
    )


def _project_starts(problem, pt0):
    """Every start projected onto the constraint set, and whether any of them moved."""
    projected = jax.vmap(problem.feasible)(pt0)
    return jnp.any(projected != pt0), projected


_project_starts_jit = eqx.filter_jit(_project_starts)


@functools.lru_cache(maxsize=64)
def _compiled_runner(solver, max_epochs):
    """One compiled call for a whole fit: project the starts, run them (vmapped), pick the
    best and post-process it (`_post`); the least-squares solvers hand their last
    linearisation to the covariance, so it costs no extra Jacobian."""
    if isinstance(solver, str) and solver in _LSQ:
        one = lambda pr, pt, px, tl, tg, rt: run_least_squares(  # noqa: E731
            pr, solver, pt, px, max_epochs, tl, tg, rt
        )
    else:
        optimiser = adam() if solver == "adam" else solver
        one = lambda pr, pt, px, tl, tg, rt: run_first_order(  # noqa: E731
            pr, optimiser, pt, px, max_epochs, tl, tg
        )

    @eqx.filter_jit
    def run(problem, pt0, px0, tol_loss, tol_grad, rtol):
        moved, pt0 = _project_starts(problem, pt0)
        *out, blocks = jax.vmap(one, in_axes=(None, 0, 0, None, None, None))(
            problem, pt0, px0, tol_loss, tol_grad, rtol
        )
        pt, px, C = out[:3]
        best = jnp.argmin(jnp.where(jnp.isfinite(C), C, jnp.inf))
        if blocks is not None:
            blocks = jax.tree_util.tree_map(lambda a: a[best], blocks)
        return moved, tuple(out), best, _post(problem, pt[best], px[best], blocks)

    return run


def _starts(problem, pt, C, code):
    thetas = jax.vmap(lambda p: problem.theta_of(p))(pt)
    return {
        "theta": thetas,
        "loss": np.asarray(C),
        "stop_reason": [StopReason(int(c)) for c in np.asarray(code)],
    }


def _run_optimistix(problem, solver, pt, px, max_epochs, rtol, proj):
    """An optimistix least-squares solve on the free variables with the closed-form
    Jacobian (forward sensitivities) as the JVP of the residual function.

    Box constraints: optimistix has no bounds, so an active-set loop wraps the solves.
    Each solve evaluates the residuals at the projected point P(y), so the model is only
    ever simulated with feasible parameters; afterwards every entry at a bound whose
    gradient points outwards is fixed at the bound (removed from the variables) and the
    rest is solved again, until no bound is violated. The returned point is feasible and
    satisfies the optimality conditions on the box; no reparametrisation (a sigmoid would
    stall at an active bound).
    """

    total_steps = 0
    free = np.ones(pt.shape[0], bool)
    for _ in range(pt.shape[0] + 1):
        sub = _restrict(problem, pt, free)
        sol = _optx_solve(sub, solver, pt[free], px, max_epochs)
        pt = pt.at[free].set(sub.feasible(sol.value[0]))
        px = sol.value[1]
        total_steps += int(sol.stats["num_steps"])
        if problem.lower is None:
            break
        _, g_t, _ = problem.value_and_grad(pt, px)
        at_lo, at_hi = np.asarray(pt <= problem.lower), np.asarray(pt >= problem.upper)
        push_out = (at_lo & (np.asarray(g_t) > 0)) | (at_hi & (np.asarray(g_t) < 0))
        new_free = free & ~push_out
        if (new_free == free).all():
            break
        free = new_free
    C = jnp.sum(problem.residuals(pt, px) ** 2)
    if sol.result == optx.RESULTS.successful:
        code = StopReason.CONVERGED
    elif sol.result == optx.RESULTS.max_steps_reached:
        code = StopReason.MAX_EPOCHS
    else:
        code = StopReason.NO_PROGRESS
    if not bool(jnp.isfinite(C)):
        code = StopReason.DIVERGED
    hist = np.full((max_epochs + 1, 2 + pt.shape[0]), np.nan)
    hist[0, 0] = float(C)
    hist[0, 2:] = np.asarray(pt)
    return pt, px, C, jnp.array(code.value), jnp.array(total_steps), jnp.asarray(hist)


def _restrict(problem, pt, free):
    """The same problem with the entries of p_theta outside `free` fixed at their values."""
    if free.all():
        return problem
    base = problem.theta_base.at[np.asarray(problem.theta_free, int)].set(pt)
    lower = None if problem.lower is None else problem.lower[free]
    upper = None if problem.upper is None else problem.upper[free]
    # theta_free is a static field (not a pytree leaf), so eqx.tree_at cannot replace it.
    return dataclasses.replace(
        problem,
        theta_base=base,
        theta_free=tuple(np.asarray(problem.theta_free)[free].tolist()),
        lower=lower,
        upper=upper,
    )


@eqx.filter_custom_jvp
def _residuals(p_theta, p_x0, *, problem):
    return problem.residuals(problem.feasible(p_theta), p_x0).reshape(-1)


@_residuals.def_jvp
def _residuals_jvp(primals, tangents, *, problem):
    """The closed-form Jacobian (forward sensitivities) applied to the tangent."""
    p_theta, p_x0 = primals
    d_theta, d_x0 = tangents
    r, Jt, Jx = problem.jacobian(problem.feasible(p_theta), p_x0)
    dr = jnp.zeros(r.shape, r.dtype)
    if d_theta is not None:
        dr = dr + jnp.einsum("nrp,p->nr", Jt, d_theta)
    if d_x0 is not None:
        dr = dr + jnp.einsum("nrm,nm->nr", Jx, d_x0)
    return r.reshape(-1), dr.reshape(-1)


def _optx_residuals(y, problem):
    """Residuals for optimistix: a module-level function with the problem as `args`, so
    optimistix's jit cache hits across calls."""
    return _residuals(*y, problem=problem)


def _optx_solve(problem, solver, pt, px, max_epochs):
    return optx.least_squares(
        _optx_residuals, solver, (pt, px), args=problem, max_steps=max_epochs, throw=False
    )


def _post(problem, pt, px, blocks=None):
    """Everything `FitResult` needs from the solution (traced inside the fit's compiled
    call; `blocks` as for `covariance_blocks`)."""
    theta = problem.theta_of(pt)
    X0 = problem.x0_of(px)
    _, zhat = _simulate(problem.model, theta, X0, problem.u, True)
    sse, S_inv, x_diag, identifiable = covariance_blocks(problem, pt, px, blocks)
    n_free = pt.shape[0] + px.size
    zs = problem.z
    met = {
        "rmse": _metrics.rmse(zs, zhat),
        "nrmse": _metrics.nrmse(zs, zhat),
        "fit_percent": _metrics.fit_percent(zs, zhat),
        "r2": _metrics.r2(zs, zhat),
        "aic": _metrics.aic(zs, zhat, n_free),
    }
    return theta, X0, zhat - zs, sse, S_inv, x_diag, identifiable, met, pt, px


_post_jit = eqx.filter_jit(_post)


def _unravel_rows(rows, like, squeeze=False):
    """Rows of flattened parameters (E, n) as the pytree `like` with a leading axis E
    (dropped with `squeeze`): the numpy inverse of `ravel_pytree`, without a JAX call."""
    leaves, treedef = jax.tree_util.tree_flatten(like)
    out, start = [], 0
    for leaf in leaves:
        size = int(np.size(leaf))
        block = rows[:, start : start + size].reshape(rows.shape[0], *np.shape(leaf))
        out.append(block[0] if squeeze else block)
        start += size
    return jax.tree_util.tree_unflatten(treedef, out)


def _result(problem, data, batched, post, C, code, epochs, hist, wall, starts, best):
    theta, X0, e, sse, S_inv, x_diag, identifiable, met, pt, px = post
    met = {k: (float(v) if k == "aic" else np.asarray(v)) for k, v in met.items()}
    n_free = pt.shape[0] + px.size
    dof = max(e.size - n_free, 1)
    # sigma^2 (J_e^T Q J_e)^{-1} with J = Q^{1/2} J_e / sqrt(N T): sigma^2/(N T) = SSE_r/dof.
    s2 = float(sse) / dof
    cov = np.asarray(S_inv) * s2
    identifiable = np.asarray(identifiable)
    if not identifiable.all():
        bad = [
            str(n)
            for n, ok in zip(np.asarray(_all_names(theta))[list(problem.theta_free)], identifiable)
            if not ok
        ]
        warnings.warn(
            f"the Jacobian is rank-deficient at the solution: {bad} do not change the "
            "outputs there (not identifiable from these data); their std is inf.",
            stacklevel=3,
        )
        cov[~identifiable, :] = np.inf
        cov[:, ~identifiable] = np.inf
    flat_std = np.zeros(problem.theta_base.shape)
    flat_std[list(problem.theta_free)] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    theta = jax.tree_util.tree_map(np.asarray, theta)
    std = _unravel_rows(flat_std[None], theta, squeeze=True)
    ci95 = (
        jax.tree_util.tree_map(lambda v, s: v - 1.96 * s, theta, std),
        jax.tree_util.tree_map(lambda v, s: v + 1.96 * s, theta, std),
    )
    x0_std = np.zeros(X0.shape)
    x0_std[:, list(problem.x0_free)] = np.sqrt(np.maximum(np.asarray(x_diag) * s2, 0.0))
    names = tuple(np.asarray(_all_names(theta))[list(problem.theta_free)].tolist())
    valid = ~np.isnan(hist[:, 0])
    base = np.asarray(problem.theta_base)
    flat_path = np.broadcast_to(base, (int(valid.sum()), base.shape[0])).copy()
    flat_path[:, list(problem.theta_free)] = hist[valid, 2:]
    history = {
        "loss": hist[valid, 0],
        "grad_norm": hist[valid, 1],
        "theta": _unravel_rows(flat_path, theta),
    }
    X0, e = np.asarray(X0), np.asarray(e)
    if not batched:
        X0, e, x0_std = X0[0], e[0], x0_std[0]
    return FitResult(
        theta=theta,
        x0=X0,
        loss=C,
        stop_reason=StopReason(code),
        epochs=epochs,
        wall_time=wall,
        history=history,
        residuals=e,
        names=names,
        covariance=cov,
        std=std,
        ci95=ci95,
        x0_std=x0_std,
        metrics=met,
        starts=starts,
        best=best,
    )
