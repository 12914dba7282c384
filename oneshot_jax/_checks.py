"""Input validation shared by every public entry point.

Every check runs on shapes (always static) and, where the arrays are concrete, on values
(NaN, inf, positive semi-definiteness). Errors are `ValueError`s that name the argument
and the shape or range that was expected, so that nothing reaches a tracing error.
"""

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(arrays))


def _as_float(a, name):
    """`a` as a floating array in JAX's canonical dtype. Host data (NumPy arrays, lists)
    stay NumPy arrays, so validation costs no device transfer or eager JAX call; the
    compiled functions take them as they are."""
    try:
        if isinstance(a, jax.Array):
            a = jnp.asarray(a)
        else:
            a = np.asarray(a)
            a = a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{name}` must hold real numbers, got {type(a).__name__}: {err}") from err
    if a.dtype == object:
        raise ValueError(f"`{name}` must hold real numbers, got dtype object.")
    if jnp.issubdtype(a.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must hold real numbers, got dtype {a.dtype}.")
    if not jnp.issubdtype(a.dtype, jnp.inexact):
        if not (jnp.issubdtype(a.dtype, jnp.integer) or a.dtype == jnp.bool_):
            raise ValueError(f"`{name}` must hold real numbers, got dtype {a.dtype}.")
        a = a.astype(jnp.result_type(float))
    return a


def check_finite(a, name):
    if is_concrete(a) and not bool(np.all(np.isfinite(np.asarray(a)))):
        raise ValueError(f"`{name}` contains NaN or inf values.")


def as_theta(theta):
    """Leaves of `theta` as floating JAX arrays (integers are promoted, not rejected)."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    if not leaves:
        raise ValueError("`theta` must contain at least one array leaf.")
    leaves = [_as_float(leaf, "theta") for leaf in leaves]
    for leaf in leaves:
        check_finite(leaf, "theta")
    return jax.tree_util.tree_unflatten(treedef, leaves)


@functools.lru_cache(maxsize=256)
def _cached_eval_shape(fn, x, u, theta_leaves, treedef):
    return jax.eval_shape(fn, x, u, jax.tree_util.tree_unflatten(treedef, theta_leaves))


def _abstract_call(fn, x, u, theta):
    """`jax.eval_shape(fn, x, u, theta)`, cached per function and abstract arguments, so
    repeated calls with the same model and shapes do not trace the model again."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    structs = tuple(jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)) for a in leaves)
    try:
        hash(fn)
    except TypeError:  # an unhashable callable: no caching
        return jax.eval_shape(fn, x, u, theta)
    return _cached_eval_shape(fn, x, u, structs, treedef)


class Data(NamedTuple):
    theta: object
    x0: jax.Array
    u: jax.Array
    z: jax.Array | None
    weight: jax.Array | None
    batched: bool


def check_weight(weight, n_z, dtype):
    """`weight` as a (n_z,) vector (diagonal Q) or an (n_z, n_z) PSD matrix; None stays None."""
    if weight is None:
        return None
    w = _as_float(weight, "weight").astype(dtype)
    if w.shape not in ((n_z,), (n_z, n_z)):
        raise ValueError(
            f"`weight` must have shape ({n_z},) (a diagonal Q) or ({n_z}, {n_z}) "
            f"(a PSD matrix Q), got shape {w.shape}."
        )
    check_finite(w, "weight")
    if is_concrete(w):
        wn = np.asarray(w, dtype=np.float64)
        scale = max(float(np.max(np.abs(wn))), 1.0e-300)
        if w.ndim == 1:
            if np.any(wn < 0):
                raise ValueError("`weight` (diagonal of Q) must be non-negative.")
        else:
            if not np.allclose(wn, wn.T, rtol=1e-10, atol=1e-12 * scale):
                raise ValueError("`weight` must be a symmetric matrix Q.")
            if np.min(np.linalg.eigvalsh(wn)) < -1e-10 * scale:
                raise ValueError("`weight` must be positive semi-definite (Q >= 0, eq. 4).")
    return w


def check_data(model, theta, x0, u, z=None, weight=None) -> Data:
    """Validate (theta, x0, u, z, weight) for `model` and return them canonicalised.

    Single trajectory: x0 (n_x,), u (T, n_u), z (T, n_z). Several trajectories sharing
    theta (the paper's footnote 1): x0 (N, n_x), u (N, T, n_u), z (N, T, n_z).
    """
    theta = as_theta(theta)
    x0 = _as_float(x0, "x0")
    if x0.ndim not in (1, 2):
        raise ValueError(
            "`x0` must have shape (n_x,) for one trajectory or (N, n_x) for N "
            f"trajectories, got shape {x0.shape}."
        )
    batched = x0.ndim == 2
    u = _as_float(u, "u")
    lead = x0.shape[:1] if batched else ()
    if u.ndim != len(lead) + 2 or u.shape[: len(lead)] != lead:
        want = f"({x0.shape[0]}, T, n_u)" if batched else "(T, n_u)"
        raise ValueError(
            f"`u` must have shape {want} to match `x0` of shape {x0.shape}, got shape {u.shape}."
        )
    T = u.shape[-2]
    if T < 1:
        raise ValueError(f"`u` must hold at least one sample (T >= 1), got shape {u.shape}.")
    if batched and x0.shape[0] < 1:
        raise ValueError("`x0` must hold at least one trajectory (N >= 1).")
    check_finite(x0, "x0")
    check_finite(u, "u")

    # Trace the user's functions once on abstract values, so that a step that changes the
    # state's shape or dtype is reported here and not as an error deep inside a scan.
    x_1 = jax.ShapeDtypeStruct(x0.shape[len(lead) :], x0.dtype)
    u_1 = jax.ShapeDtypeStruct(u.shape[len(lead) + 1 :], u.dtype)
    try:
        x_next = _abstract_call(model.step, x_1, u_1, theta)
        z_hat = _abstract_call(model.observe, x_1, u_1, theta)
    except Exception as err:  # noqa: BLE001 - re-raised with the arguments' shapes
        raise ValueError(
            f"calling the model on a state of shape {x_1.shape} (from `x0` of shape "
            f"{x0.shape}) and an input of shape {u_1.shape} (from `u` of shape {u.shape}) "
            f"failed: {type(err).__name__}: {err}"
        ) from err
    if not isinstance(x_next, jax.ShapeDtypeStruct) or x_next.shape != x_1.shape:
        shape = getattr(x_next, "shape", type(x_next).__name__)
        raise ValueError(
            f"`model.step` must return a state of shape {x_1.shape} (the shape of x0), got {shape}."
        )
    if x_next.dtype != x_1.dtype:
        raise ValueError(
            f"`model.step` must keep the state's dtype {x_1.dtype} (the dtype of x0), "
            f"got {x_next.dtype}. Pass x0 and theta in the same precision."
        )
    if not isinstance(z_hat, jax.ShapeDtypeStruct) or z_hat.ndim != 1:
        shape = getattr(z_hat, "shape", type(z_hat).__name__)
        raise ValueError(
            f"`model.observe` must return a 1-D output z of shape (n_z,), got {shape}."
        )
    n_z = z_hat.shape[0]

    if z is not None:
        z = _as_float(z, "z").astype(z_hat.dtype)
        want = (*lead, T, n_z)
        if z.shape != want:
            raise ValueError(
                f"`z` must have shape {want} (leading axes of `u`, n_z = {n_z} outputs of "
                f"`model.observe`), got shape {z.shape}."
            )
        check_finite(z, "z")
    weight = check_weight(weight, n_z, z_hat.dtype)
    return Data(theta, x0, u, z, weight, batched)


def check_penalty(penalty, penalty_weight):
    if penalty is not None and not callable(penalty):
        raise ValueError(f"`penalty` must be callable h(x, theta) -> scalar, got {penalty!r}.")
    if penalty is None:
        return None, 0.0
    pw = penalty_weight
    msg = f"`penalty_weight` must be a finite real scalar, got {penalty_weight!r}."
    try:
        ok = np.ndim(pw) == 0 and not np.iscomplexobj(pw)
        ok = ok and (not is_concrete(pw) or bool(np.isfinite(float(pw))))
    except (TypeError, ValueError) as err:
        raise ValueError(msg) from err
    if not ok:
        raise ValueError(msg)
    return penalty, pw


def check_strategy(strategy):
    if strategy not in ("auto", "jacobian", "vjp"):
        raise ValueError(f"`strategy` must be 'auto', 'jacobian' or 'vjp', got {strategy!r}.")
    return strategy


filter_jit = eqx.filter_jit
