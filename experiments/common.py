"""Shared experiment code: one solver spec `{name, kwargs}` in, one `Estimate` out.

A solver spec is what the `solver/` config group holds (and what the satellite study lists
for its baselines), so every experiment runs every solver the same way:

- `name: adam | lbfgs | gauss_newton | levenberg_marquardt`: `oneshot_jax.fit` with the
  solver object `oneshot_jax.Adam(**kwargs)`, `LBFGS(**kwargs)`, `GaussNewton(**kwargs)`
  or `LevenbergMarquardt(**kwargs)`; `kwargs` are that object's options (`max_steps`,
  `rtol`, `lr_theta`, `tol_grad`, ...). The fit records its path itself
  (`FitResult.history`), which the figures draw.
- `name: scipy`: `scipy.optimize.minimize` on the same multi-step cost C (eq. 5);
  kwargs `method` (`SLSQP`, `trust-constr`, `L-BFGS-B`, ...), `jac` (`closed_form`: the
  one-shot gradient of `oneshot_jax.value_and_grad`; `fd`: scipy's finite differences of
  `oneshot_jax.loss`), `fd_scheme` (`2-point`), `maxiter`, `tol` (null: scipy's default),
  `scale` (false: the raw problem; true: variables divided by their initial magnitudes,
  theta entry-wise and x0 by max|x0|, and C divided by its initial value) and `options`
  (passed on to scipy). Box constraints from `oneshot_jax.constraints` become scipy
  bounds; the path is recorded through scipy's callback.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.internal import flat_host, unflatten_rows

SOLVER_CLASSES = {
    "adam": oj.Adam,
    "lbfgs": oj.LBFGS,
    "gauss_newton": oj.GaussNewton,
    "levenberg_marquardt": oj.LevenbergMarquardt,
}
SCIPY_KEYS = ("method", "jac", "fd_scheme", "maxiter", "tol", "scale", "options")


# ------------------------------------------------------------------------------- specs


def _spec(spec) -> tuple[str, dict]:
    """(name, kwargs) of a spec: a `config.SolverConfig` or a mapping."""
    if isinstance(spec, Mapping):
        return spec["name"], dict(spec.get("kwargs") or {})
    return spec.name, dict(spec.kwargs or {})


def make_solver(name: str, kwargs: Mapping) -> oj.AbstractSolver:
    """The library solver object of a spec (`ValueError` naming a bad option)."""
    cls = SOLVER_CLASSES[name]
    valid = [f.name for f in dataclasses.fields(cls) if f.init]
    unknown = sorted(set(kwargs) - set(valid))
    if unknown:
        raise ValueError(
            f"solver {name!r} ({cls.__name__}) got unknown kwargs {unknown}; valid: {valid}."
        )
    return cls(**kwargs)


def plus_minus(value, std, decimals: int, std_decimals: int | None = None) -> str:
    """ "value ± std" for a results table with `decimals` decimals (`std_decimals` for the
    standard error, the same by default), but a standard error too large for them (a
    parameter the data barely determine: 5.6e16) or not finite in three significant
    digits. None (a NaN after `to_jsonable`, strict JSON) reads as NaN."""
    value = math.nan if value is None else float(value)
    std = math.nan if std is None else float(std)
    big = not math.isfinite(std) or std >= 1e4
    places = decimals if std_decimals is None else std_decimals
    return f"{value:.{decimals}f} ± " + (f"{std:.3g}" if big else f"{std:.{places}f}")


def start(cfg, outdir, title: str):
    """The common start of an experiment's `run()`: float64 checked, the configured
    solver built, the output folder made. Returns (solver, outdir, start time)."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            f"the {title} experiment needs float64: call "
            "jax.config.update('jax_enable_x64', True) before run() (experiments/run.py does)."
        )
    solver = make_solver(cfg.solver.name, cfg.solver.kwargs)
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    return solver, outdir, time.perf_counter()


def protocol_scores(scores, pred, unit: str) -> dict:
    """The protocol's scores (`oneshot_jax.metrics.benchmark_scores` of one output) and
    the x0 its prediction used, as JSON-ready numbers; the RMSE under `rmse_<unit>`."""
    return {
        "n": int(scores.n),
        f"rmse_{unit}": float(scores.rmse[0]),
        "nrmse": float(scores.nrmse[0]),
        "r2": float(scores.r2[0]),
        "fit_percent": float(scores.fit_percent[0]),
        "x0": [float(v) for v in np.asarray(pred.x0)],
    }


SCIPY_METHODS = (
    "Nelder-Mead",
    "Powell",
    "CG",
    "BFGS",
    "Newton-CG",
    "L-BFGS-B",
    "TNC",
    "COBYLA",
    "COBYQA",
    "SLSQP",
    "trust-constr",
    "dogleg",
    "trust-ncg",
    "trust-exact",
    "trust-krylov",
)


def check_solver(name: str, kwargs: Mapping, key: str = "solver") -> None:
    """Raise a `ValueError` naming the option (under `key`, where the spec sits in the
    configuration) when a spec cannot run."""
    kwargs = dict(kwargs or {})
    if name in SOLVER_CLASSES:
        steps = kwargs.get("max_steps")
        if isinstance(steps, int) and not isinstance(steps, bool) and steps == 0:
            # (the library takes 0, a fit that evaluates its start; a study reporting it
            # would present the start as the estimate)
            raise ValueError(
                f"`{key}.kwargs.max_steps` must be an integer >= 1 in an experiment (0 takes "
                "no step, and the tables would report the start as the fit), got 0."
            )
        try:
            make_solver(name, kwargs)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{key}.kwargs of {name!r}: {err}") from None
        return

    def bad(option, expected):
        raise ValueError(f"`{key}.kwargs.{option}` must be {expected}, got {kwargs[option]!r}.")

    unknown = sorted(set(kwargs) - set(SCIPY_KEYS))
    if unknown:
        raise ValueError(
            f"{key}: solver 'scipy' got unknown kwargs {unknown}; valid: {list(SCIPY_KEYS)}."
        )
    if "method" in kwargs and str(kwargs["method"]).lower() not in {
        m.lower() for m in SCIPY_METHODS
    }:
        bad("method", "a scipy.optimize.minimize method (" + ", ".join(SCIPY_METHODS) + ")")
    if kwargs.get("jac", "closed_form") not in ("closed_form", "fd"):
        bad("jac", "'closed_form' or 'fd'")
    if kwargs.get("fd_scheme", "2-point") not in ("2-point", "3-point"):
        bad("fd_scheme", "'2-point' or '3-point'")
    if kwargs.get("maxiter") is not None and (
        isinstance(kwargs["maxiter"], bool)
        or not isinstance(kwargs["maxiter"], int)
        or kwargs["maxiter"] < 1
    ):
        bad("maxiter", "an integer >= 1 (or null)")
    tol = kwargs.get("tol")
    if tol is not None and (
        isinstance(tol, bool)
        or not isinstance(tol, (int, float))
        or not math.isfinite(tol)
        or tol <= 0
    ):
        bad("tol", "a finite number > 0 (or null: scipy's default)")
    if not isinstance(kwargs.get("scale", False), bool):
        bad("scale", "true or false")
    if not isinstance(kwargs.get("options") or {}, Mapping):
        bad("options", "a mapping of scipy options")


def same_solver(a, b) -> bool:
    """True when two specs run the same solver with the same settings (labels ignored)."""
    return _spec(a) == _spec(b)


def to_jsonable(obj):
    """Recursively turn arrays, numpy scalars and dataclasses into JSON values; non-finite
    floats become None (strict JSON)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, (np.ndarray, jax.Array)):
        return to_jsonable(np.asarray(obj).tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


# ----------------------------------------------------------------------------- estimate


@dataclasses.dataclass
class Estimate:
    """What every solver returns. `theta` keeps the structure of `theta0` (numpy leaves);
    `theta_flat` is its flattening (leaf order). `time_s` is the optimisation time:
    `FitResult.wall_time` for the library (compilation included on the first call of a
    shape), the `minimize` call for scipy (objective compiled before the clock starts).
    `path` holds the theta iterates (rows, flattened; start first, estimate last) and
    `path_steps` the step of each row (the library thins long paths evenly); `result`
    the library's `FitResult` (None for scipy), which a run saves (`FitResult.save`)."""

    theta: Any
    theta_flat: np.ndarray
    x0: np.ndarray
    loss: float
    iterations: int
    time_s: float
    stop_reason: str
    success: bool
    message: str
    nfev: int | None = None
    theta_std: np.ndarray | None = None
    path: np.ndarray | None = None
    path_steps: np.ndarray | None = None
    result: Any = None  # (the library's `FitResult`, which a run saves; None for scipy)

    def summary(self) -> dict:
        """JSON-friendly summary (no path)."""
        return to_jsonable(
            {
                "theta": self.theta,
                "x0": self.x0,
                "loss": self.loss,
                "iterations": self.iterations,
                "time_s": self.time_s,
                "stop_reason": self.stop_reason,
                "success": self.success,
                "message": self.message,
                "nfev": self.nfev,
                "theta_std": self.theta_std,
            }
        )


def flat_rows(tree) -> np.ndarray:
    """A pytree whose leaves have a leading axis of rows, as one (rows, n) array (the
    row-wise `flat_host`)."""
    leaves = [np.asarray(a) for a in jax.tree_util.tree_leaves(tree)]
    return np.concatenate([a.reshape(a.shape[0], -1) for a in leaves], axis=1)


def from_fit(result: oj.FitResult) -> Estimate:
    """An `Estimate` of a `FitResult`, with its recorded path."""
    h = result.history
    return Estimate(
        theta=jax.tree_util.tree_map(np.asarray, result.theta),
        theta_flat=flat_host(result.theta).astype(np.float64),
        x0=np.asarray(result.x0),
        loss=float(result.loss),
        iterations=int(result.num_steps),
        time_s=float(result.wall_time),
        stop_reason=result.status,
        success=bool(result.success),
        message=result.message,
        theta_std=flat_host(result.std),
        path=flat_rows(h.theta),
        path_steps=np.asarray(h.step) + _stage_offsets(h),
        result=result,
    )


def _stage_offsets(h) -> np.ndarray:
    """Steps counted from the start of the fit (a sequence of solvers counts each stage
    from 0)."""
    stage = np.asarray(h.stage)
    step = np.asarray(h.step)
    offset = np.zeros_like(step)
    for s in np.unique(stage)[1:]:
        offset[stage >= s] += step[stage == s - 1].max(initial=0)
    return offset


# ------------------------------------------------------------------------------ library


def _solve_library(model, theta0, x0, u, z, name, kw, constraints, estimate_x0, history):
    r = oj.fit(
        model,
        theta0,
        x0,
        u,
        z,
        solver=make_solver(name, kw),
        constraints=constraints,
        estimate_x0=estimate_x0,
        history=history,
    )
    return from_fit(r)


# -------------------------------------------------------------------------------- scipy


@eqx.filter_jit
def _objective(model, estimate_x0, with_grad, p, theta_like, x0_fixed, u, z):
    """C(p) (eq. 5), and with `with_grad` its one-shot gradient (eq. 17, 20), flattened;
    p = (theta flattened, x0 if estimated)."""
    flat, unravel = ravel_pytree(theta_like)
    n_theta = flat.shape[0]
    theta = unravel(p[:n_theta])
    x0 = p[n_theta:].reshape(x0_fixed.shape) if estimate_x0 else x0_fixed
    if not with_grad:
        return oj.loss(model, theta, x0, u, z)
    C, (g_theta, g_x0) = oj.value_and_grad(model, theta, x0, u, z)
    g = ravel_pytree(g_theta)[0]
    return C, (jnp.concatenate([g, jnp.ravel(g_x0)]) if estimate_x0 else g)


# The scipy methods that take no gradient (`jac` is then not used).
GRADIENT_FREE = ("nelder-mead", "powell", "cobyla", "cobyqa")


def scipy_words(kwargs) -> tuple[str, str, str]:
    """What a scipy baseline's options make of it, in words: its method, its gradient
    ("closed-form gradient", "finite differences", or "no gradient" for a gradient-free
    method) and whether the problem is "scaled" or "raw"."""
    method = str(kwargs.get("method", "SLSQP"))
    if method.lower() in GRADIENT_FREE:
        gradient = "no gradient"
    elif kwargs.get("jac", "closed_form") == "closed_form":
        gradient = "closed-form gradient"
    else:
        gradient = "finite differences"
    return method, gradient, "scaled" if kwargs.get("scale", False) else "raw"


def scipy_label(kwargs) -> str:
    """A scipy baseline's label from its options (`scipy_words`): "SLSQP + finite
    differences (raw)"."""
    method, gradient, scaling = scipy_words(kwargs)
    return f"{method} + {gradient} ({scaling})"


def _solve_scipy(model, theta0, x0, u, z, kw, constraints, estimate_x0):
    method = kw.get("method", "SLSQP")
    jac = kw.get("jac", "closed_form")
    scheme = kw.get("fd_scheme", "2-point")
    options = dict(kw.get("options") or {})
    if kw.get("maxiter") is not None:
        options["maxiter"] = int(kw["maxiter"])
    tol = kw.get("tol")
    scale = bool(kw.get("scale", False))

    like = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), theta0)
    flat0 = flat_host(theta0).astype(np.float64)
    x0 = np.asarray(x0, dtype=np.float64)
    n_t = flat0.size
    uj, zj, x0j = (jnp.asarray(a, dtype=jnp.float64) for a in (u, z, x0))

    lo = np.full(n_t, -np.inf)
    hi = np.full(n_t, np.inf)
    proj = oj.constraints.combine(constraints)
    if proj is not None:
        if proj.bounds is None:
            raise ValueError("the scipy baselines support box constraints only.")
        blo, bhi = proj.bounds(like)
        lo, hi = flat_host(blo), flat_host(bhi)
    flat0 = np.clip(flat0, lo, hi)
    if estimate_x0:
        p0 = np.concatenate([flat0, x0.ravel()])
        lo = np.concatenate([lo, np.full(x0.size, -np.inf)])
        hi = np.concatenate([hi, np.full(x0.size, np.inf)])
    else:
        p0 = flat0

    if scale:
        s_t = np.where(np.abs(flat0) > 0, np.abs(flat0), 1.0)
        xmax = float(np.max(np.abs(x0))) if x0.size else 0.0
        s_x = np.full(x0.size if estimate_x0 else 0, xmax if xmax > 0 else 1.0)
        s = np.concatenate([s_t, s_x])
    else:
        s = np.ones_like(p0)

    def value(p):
        return float(_objective(model, estimate_x0, False, jnp.asarray(p), like, x0j, uj, zj))

    def value_grad(p):
        C, g = _objective(model, estimate_x0, True, jnp.asarray(p), like, x0j, uj, zj)
        return float(C), np.asarray(g)

    C0 = value(p0)  # also compiles the objective before the clock starts
    c = C0 if (scale and math.isfinite(C0) and C0 > 0) else 1.0
    if jac == "closed_form":
        value_grad(p0)  # compile the gradient before the clock starts

        def fun(q):
            C, g = value_grad(q * s)
            return C / c, g * s / c

        jac_arg = True
    else:

        def fun(q):
            return value(q * s) / c

        jac_arg = scheme
    path = [p0.copy()]

    def callback(xk, *_):
        path.append(np.asarray(xk, dtype=np.float64) * s)

    bounds = scipy.optimize.Bounds(lo / s, hi / s) if np.isfinite(np.r_[lo, hi]).any() else None
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        # (trust-constr's note that its quasi-Newton update was skipped: the run's outcome,
        # success or not, is reported with scipy's own message below)
        warnings.filterwarnings("ignore", message="delta_grad == 0.0", category=UserWarning)
        res = scipy.optimize.minimize(
            fun,
            p0 / s,
            jac=jac_arg,
            method=method,
            bounds=bounds,
            tol=tol,
            options=options,
            callback=callback,
        )
    elapsed = time.perf_counter() - t0
    p = np.asarray(res.x, dtype=np.float64) * s
    theta = unflatten_rows(p[None, :n_t], theta0, squeeze=True)
    x0_hat = p[n_t:].reshape(x0.shape) if estimate_x0 else x0
    path = np.stack(path)[:, :n_t]
    return Estimate(
        theta=theta,
        theta_flat=p[:n_t].copy(),
        x0=np.asarray(x0_hat),
        loss=value(p),
        iterations=int(getattr(res, "nit", -1) or -1),
        time_s=elapsed,
        stop_reason=f"scipy: {res.message}",
        success=bool(res.success),
        message=str(res.message),
        nfev=int(getattr(res, "nfev", -1)),
        path=path,
        path_steps=np.arange(len(path)),
    )


# --------------------------------------------------------------------------------- entry


def solve(
    model, theta0, x0, u, z, spec, *, constraints=None, estimate_x0=True, history=1000
) -> Estimate:
    """Minimise the multi-step cost C of `model` on (u, z) with the solver `spec`.

    **Arguments:**

    - `model`, `theta0`, `x0`, `u`, `z`: as for `oneshot_jax.fit` (one trajectory or N
        stacked ones).
    - `spec`: a `config.SolverConfig` or a mapping `{name, kwargs}`.
    - `constraints`: a projection from `oneshot_jax.constraints` (box-type for scipy).
    - `estimate_x0`: as for `oneshot_jax.fit`.
    - `history`: rows of the recorded path (library solvers).

    **Returns:**

    An `Estimate`.
    """
    name, kw = _spec(spec)
    if name == "scipy":
        return _solve_scipy(model, theta0, x0, u, z, kw, constraints, estimate_x0)
    return _solve_library(model, theta0, x0, u, z, name, kw, constraints, estimate_x0, history)
