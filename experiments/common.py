"""Shared experiment code: one solver spec `{name, kwargs}` in, one `Estimate` out.

A solver spec is what the `solver/` config group holds (and what an experiment lists for
its baselines), so every experiment can run every solver the same way:

- `name: adam`: Algorithm 1 through `oneshot_jax.fit` with `oneshot_jax.adam`;
  kwargs `lr_theta, lr_x0, b1, b2, eps` (the optimiser) and `max_epochs, tol_loss,
  tol_grad` (Algorithm 1's E_max, epsilon, delta).
- `name: gauss_newton` / `levenberg_marquardt`: `oneshot_jax.fit` with the library's
  structured least-squares solvers; kwargs `max_epochs, rtol, tol_loss, tol_grad`.
- `name: scipy`: `scipy.optimize.minimize` on the same multi-step cost C (eq. 5);
  kwargs `method` (`SLSQP`, `trust-constr`, `L-BFGS-B`, ...), `jac` (`closed_form`: the
  one-shot gradient of `oneshot_jax.value_and_grad`; `fd`: scipy's finite differences of
  `oneshot_jax.loss`), `fd_scheme` (`2-point`), `maxiter`, `tol` (null: scipy's default),
  `scale` (false: the raw problem; true: variables divided by their initial magnitudes,
  theta entry-wise and x0 by max|x0|, and C divided by its initial value) and `options`
  (passed on to scipy). Box constraints from `oneshot_jax.constraints` become scipy
  bounds.

Every solver can also record its path (the theta iterates), for the figures: Adam through
a recording optax transform that `fit` runs itself, scipy through its callback, and the
least-squares solvers by chaining one-epoch fits (exact for Gauss-Newton, which keeps no
state between iterations; for Levenberg-Marquardt the damping restarts at every link, so
that path is an approximation of the real one, whose end point is reported).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import scipy.optimize

import oneshot_jax as oj

LIBRARY_SOLVERS = ("adam", "gauss_newton", "levenberg_marquardt")
SOLVER_NAMES = (*LIBRARY_SOLVERS, "scipy")
_ADAM_KEYS = ("lr_theta", "lr_x0", "b1", "b2", "eps")
_FIT_KEYS = {
    "adam": ("max_epochs", "tol_loss", "tol_grad", "strategy"),
    "gauss_newton": ("max_epochs", "rtol", "tol_loss", "tol_grad"),
    "levenberg_marquardt": ("max_epochs", "rtol", "tol_loss", "tol_grad"),
}
_SCIPY_KEYS = ("method", "jac", "fd_scheme", "maxiter", "tol", "scale", "options")


# ------------------------------------------------------------------------------- helpers


def plain(node) -> Any:
    """A config node (OmegaConf DictConfig/ListConfig) as plain Python, resolved."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - hydra is a dependency
        return node
    if isinstance(node, (DictConfig, ListConfig)):
        return OmegaConf.to_container(node, resolve=True)
    return node


def solver_spec(spec) -> tuple[str, dict]:
    """Validate a solver spec `{name, kwargs}` and return `(name, kwargs)`."""
    spec = plain(spec)
    if not isinstance(spec, Mapping) or "name" not in spec:
        raise ValueError(f"a solver spec needs a `name` (one of {SOLVER_NAMES}), got {spec!r}.")
    name = spec["name"]
    if name not in SOLVER_NAMES:
        raise ValueError(f"unknown solver name {name!r}; valid: {', '.join(SOLVER_NAMES)}.")
    kwargs = dict(spec.get("kwargs") or {})
    valid = _SCIPY_KEYS if name == "scipy" else _FIT_KEYS[name] + (
        _ADAM_KEYS if name == "adam" else ())
    unknown = sorted(set(kwargs) - set(valid))
    if unknown:
        raise ValueError(f"solver {name!r} got unknown kwargs {unknown}; valid: {list(valid)}.")
    return name, kwargs


def same_solver(a, b) -> bool:
    """True when two specs run the same solver with the same settings (labels ignored)."""
    return solver_spec(a) == solver_spec(b)


def to_jsonable(obj):
    """Recursively turn arrays, numpy scalars, enums and dataclasses into JSON values;
    non-finite floats become None (strict JSON)."""
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
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if hasattr(obj, "name") and hasattr(obj, "value") and not isinstance(obj, (str, bytes)):
        return obj.name  # enums (StopReason)
    return plain(obj)


def _flatten(theta) -> np.ndarray:
    leaves = jax.tree_util.tree_leaves(theta)
    return np.concatenate([np.ravel(np.asarray(leaf, dtype=np.float64)) for leaf in leaves])


def _structure(theta):
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    return treedef, tuple(tuple(np.shape(leaf)) for leaf in leaves)


def _unflatten(treedef, shapes, flat):
    out, i = [], 0
    for shape in shapes:
        n = int(np.prod(shape, dtype=int))
        out.append(flat[i : i + n].reshape(shape))
        i += n
    return jax.tree_util.tree_unflatten(treedef, out)


@dataclasses.dataclass
class Estimate:
    """What every solver returns. `theta` keeps the structure of `theta0` (numpy leaves);
    `theta_flat` is its flattening (leaf order). `time_s` is the optimisation time:
    `FitResult.wall_time` for the library (compilation included on the first call of a
    shape), the `minimize` call for scipy (objective compiled before the clock starts)."""

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
    path_x0: np.ndarray | None = None

    def summary(self) -> dict:
        """JSON-friendly summary (no path)."""
        return to_jsonable({
            "theta": self.theta, "x0": self.x0, "loss": self.loss,
            "iterations": self.iterations, "time_s": self.time_s,
            "stop_reason": self.stop_reason, "success": self.success, "message": self.message,
            "nfev": self.nfev, "theta_std": self.theta_std,
        })


# ------------------------------------------------------------------------------ library


_RECORD: list = []


def _record_sink(params):
    _RECORD.append((np.array(params["theta"], dtype=np.float64).reshape(-1),
                    np.array(params["x0"], dtype=np.float64).reshape(-1)))


@functools.lru_cache(maxsize=32)
def _adam_transform(lr_theta, lr_x0, b1, b2, eps, record):
    """One optax object per setting, so that `fit`'s compiled loop is reused."""
    base = oj.adam(lr_theta, lr_x0, b1, b2, eps)
    if not record:
        return base

    def update(updates, state, params=None):
        # `fit` calls update once per epoch with the current iterate (also at the
        # stopping epoch, whose iterate is the one returned): record it on the host.
        jax.debug.callback(_record_sink, params)
        return base.update(updates, state, params)

    return optax.GradientTransformation(base.init, update)


def _from_fit(r) -> Estimate:
    return Estimate(
        theta=jax.tree_util.tree_map(np.asarray, r.theta), theta_flat=_flatten(r.theta),
        x0=np.asarray(r.x0), loss=float(r.loss), iterations=int(r.epochs),
        time_s=float(r.wall_time), stop_reason=r.stop_reason.name, success=bool(r.success),
        message=r.stop_reason.message, theta_std=_flatten(r.std),
    )


def _solve_library(model, u, z, theta0, x0, name, kw, constraints, estimate_x0, record):
    kw = dict(kw)
    fit_kw = {k: kw.pop(k) for k in list(kw) if k in _FIT_KEYS[name]}
    if "max_epochs" in fit_kw:
        fit_kw["max_epochs"] = int(fit_kw["max_epochs"])
    common = dict(constraints=constraints, estimate_x0=estimate_x0)
    if name == "adam":
        opt = dict(lr_theta=1e-3, lr_x0=1e-4, b1=0.9, b2=0.999, eps=1e-8)
        opt.update({k: float(v) for k, v in kw.items()})
        args = tuple(opt[k] for k in _ADAM_KEYS)
        if record:
            _RECORD.clear()
            r = oj.fit(model, u, z, theta0, x0, solver=_adam_transform(*args, True),
                       **fit_kw, **common)
            est = _from_fit(r)
            est.path = np.stack([t for t, _ in _RECORD])
            est.path_x0 = np.stack([x for _, x in _RECORD])
            _RECORD.clear()
            return est
        r = oj.fit(model, u, z, theta0, x0, solver=_adam_transform(*args, False),
                   **fit_kw, **common)
        return _from_fit(r)
    r = oj.fit(model, u, z, theta0, x0, solver=name, **fit_kw, **common)
    est = _from_fit(r)
    if record:
        est.path, est.path_x0 = _chained_path(model, u, z, theta0, x0, name, fit_kw, common)
    return est


def _chained_path(model, u, z, theta0, x0, name, fit_kw, common):
    """Iterates of a least-squares solver: one-epoch fits, each started where the last one
    stopped (see the module docstring)."""
    max_epochs = int(fit_kw.get("max_epochs", 100))
    one = {k: v for k, v in fit_kw.items() if k != "max_epochs"}
    theta, x = theta0, jnp.asarray(x0)
    path, path_x0 = [_flatten(theta0)], [np.ravel(np.asarray(x0, dtype=np.float64))]
    for _ in range(max_epochs):
        r = oj.fit(model, u, z, theta, x, solver=name, max_epochs=1, **one, **common)
        theta, x = r.theta, r.x0
        path.append(_flatten(theta))
        path_x0.append(np.ravel(np.asarray(x)))
        if r.stop_reason != oj.StopReason.MAX_EPOCHS:
            break
    return np.stack(path), np.stack(path_x0)


# -------------------------------------------------------------------------------- scipy


def _unpack(treedef, shapes, estimate_x0, p, x0_fixed):
    n_theta = sum(int(np.prod(s, dtype=int)) for s in shapes)
    theta = _unflatten(treedef, shapes, p[:n_theta])
    x0 = p[n_theta:].reshape(x0_fixed.shape) if estimate_x0 else x0_fixed
    return theta, x0


@eqx.filter_jit
def _objective(model, treedef, shapes, estimate_x0, with_grad, p, x0_fixed, u, z):
    """C(p) (eq. 5), and with `with_grad` its one-shot gradient (eq. 17, 20), flattened."""
    theta, x0 = _unpack(treedef, shapes, estimate_x0, p, x0_fixed)
    if not with_grad:
        return oj.loss(model, theta, x0, u, z)
    C, (g_theta, g_x0) = oj.value_and_grad(model, theta, x0, u, z)
    g = [jnp.ravel(leaf) for leaf in jax.tree_util.tree_leaves(g_theta)]
    if estimate_x0:
        g.append(jnp.ravel(g_x0))
    return C, jnp.concatenate(g)


def _solve_scipy(model, u, z, theta0, x0, kw, constraints, estimate_x0, record):
    kw = dict(kw)
    method = kw.get("method", "SLSQP")
    jac = kw.get("jac", "closed_form")
    if jac not in ("closed_form", "fd"):
        raise ValueError(f"scipy `jac` must be 'closed_form' or 'fd', got {jac!r}.")
    scheme = kw.get("fd_scheme", "2-point")
    options = dict(kw.get("options") or {})
    if kw.get("maxiter") is not None:
        options["maxiter"] = int(kw["maxiter"])
    tol = kw.get("tol")

    treedef, shapes = _structure(theta0)
    flat0 = _flatten(theta0)
    x0 = np.asarray(x0, dtype=np.float64)
    n_t = flat0.size
    uj, zj, x0j = (jnp.asarray(a, dtype=jnp.float64) for a in (u, z, x0))

    lo = np.full(n_t, -np.inf)
    hi = np.full(n_t, np.inf)
    proj = oj.constraints.combine(constraints)
    if proj is not None:
        if proj.bounds is None:
            raise ValueError("the scipy baselines support box constraints only.")
        blo, bhi = proj.bounds(jax.tree_util.tree_map(jnp.asarray, theta0))
        lo, hi = _flatten(blo), _flatten(bhi)
    flat0 = np.clip(flat0, lo, hi)
    if estimate_x0:
        p0 = np.concatenate([flat0, x0.ravel()])
        lo = np.concatenate([lo, np.full(x0.size, -np.inf)])
        hi = np.concatenate([hi, np.full(x0.size, np.inf)])
    else:
        p0 = flat0

    if kw.get("scale", False):
        s_t = np.where(np.abs(flat0) > 0, np.abs(flat0), 1.0)
        xmax = float(np.max(np.abs(x0))) if x0.size else 0.0
        s_x = np.full(x0.size if estimate_x0 else 0, xmax if xmax > 0 else 1.0)
        s = np.concatenate([s_t, s_x])
    else:
        s = np.ones_like(p0)

    def value(p):
        return float(_objective(model, treedef, shapes, estimate_x0, False, jnp.asarray(p),
                                x0j, uj, zj))

    def value_grad(p):
        C, g = _objective(model, treedef, shapes, estimate_x0, True, jnp.asarray(p), x0j, uj, zj)
        return float(C), np.asarray(g)

    C0 = value(p0)  # also compiles the objective before the clock starts
    c = C0 if (kw.get("scale", False) and math.isfinite(C0) and C0 > 0) else 1.0
    if jac == "closed_form":
        value_grad(p0)  # compile the gradient before the clock starts
        fun = lambda q: (lambda Cg: (Cg[0] / c, Cg[1] * s / c))(value_grad(q * s))  # noqa: E731
        jac_arg = True
    else:
        fun = lambda q: value(q * s) / c  # noqa: E731
        jac_arg = scheme
    path = [p0.copy()]

    def callback(xk, *_):
        path.append(np.asarray(xk, dtype=np.float64) * s)

    bounds = scipy.optimize.Bounds(lo / s, hi / s) if np.isfinite(np.r_[lo, hi]).any() else None
    t0 = time.perf_counter()
    res = scipy.optimize.minimize(fun, p0 / s, jac=jac_arg, method=method, bounds=bounds,
                                  tol=tol, options=options,
                                  callback=callback if record else None)
    elapsed = time.perf_counter() - t0
    p = np.asarray(res.x, dtype=np.float64) * s
    theta, x0_hat = _unpack(treedef, shapes, estimate_x0, p, x0)
    est = Estimate(
        theta=jax.tree_util.tree_map(np.asarray, theta), theta_flat=p[:n_t].copy(),
        x0=np.asarray(x0_hat), loss=value(p), iterations=int(getattr(res, "nit", -1) or -1),
        time_s=elapsed, stop_reason=f"scipy: {res.message}", success=bool(res.success),
        message=str(res.message), nfev=int(getattr(res, "nfev", -1)),
    )
    if record:
        arr = np.stack(path)
        est.path = arr[:, :n_t]
        est.path_x0 = arr[:, n_t:] if estimate_x0 else np.repeat(x0.reshape(1, -1), len(arr), 0)
    return est


# --------------------------------------------------------------------------------- entry


def solve(model, u, z, theta0, x0, spec, *, constraints=None, estimate_x0=True,
          record_path=False) -> Estimate:
    """Minimise the multi-step cost C of `model` on (u, z) with the solver `spec`.

    `u`, `z`, `x0` are as for `oneshot_jax.fit` (one trajectory or N stacked ones);
    `constraints` a projection from `oneshot_jax.constraints` (box-type for scipy);
    `record_path=True` fills `Estimate.path` (theta iterates, start first).
    """
    name, kw = solver_spec(spec)
    if name == "scipy":
        return _solve_scipy(model, u, z, theta0, x0, kw, constraints, estimate_x0, record_path)
    return _solve_library(model, u, z, theta0, x0, name, kw, constraints, estimate_x0,
                          record_path)
