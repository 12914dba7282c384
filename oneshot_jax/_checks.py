"""Validation of the arguments that the public functions share, and what is built from
them on the way.

What it checks: the data (`theta`, `x0`, `u`, `z`, `weight`, `missing`) against the
model, which it calls abstractly once so that a wrong shape is reported with the
argument's name (`check_data`); the penalty and its weight (`check_cost`); `strategy`;
the fixed entries, bounds and the x0 mask; that `fit` is not called under a JAX
transformation. What it builds: `Data` (every array promoted to one floating dtype,
ragged trajectories padded and masked by `_normalise`, the model bound to its static
arguments), the
`Cost` bundle, the masks; and it keeps, per model, structure, shapes and dtypes, what
does not depend on the values (`_STRUCTURE`), while the checks of values run on every
call.

Checks that belong to one object live with that object, not here: a solver's options in
`_solver/`, a constraint's, penalty's or regulariser's arguments in `_prox.py` (with
what `fit` checks of them on theta0), `constraints.py`, `penalties.py` and
`sparsity.py`, a model's in `_model.py`, `fit`'s and `estimate_x0`'s own keywords
where those are defined, a saved file's in `_io.py`, the loaders' in
`datasets/`, and the parallel-in-time options in `_parallel/`.

Every check runs on shapes (always static) and, where the arrays are concrete, on values
(NaN, inf, positive semi-definiteness). Errors are `ValueError`s (or `TypeError`s for an
argument of the wrong kind) that name the argument and the shape or range that was
expected, so that nothing reaches a tracing error.
"""

import contextlib
import functools
import os
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._caller_warnings import frames_to_user, warn
from ._cost import Cost
from ._indices import out_of_range
from ._masked import unmasked
from ._model import ODE_STEPS, FloatObserve, Model
from ._normalise import fill_missing, is_ragged, pad, sample_mask
from ._timing import append_intervals, check_times


def is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(arrays))


def check_tree(tree, name="theta"):
    """A ValueError naming `name` where JAX cannot flatten `tree` (a dict whose keys
    cannot be sorted against each other, {0: ..., "b": ...}): JAX's own error names no
    argument. A TypeError where `tree` is a `FitResult` (nlgreyest's habit of passing the
    estimated model): its `theta` is meant."""
    if hasattr(tree, "stop_reason") and hasattr(tree, "theta") and hasattr(tree, "x0"):
        x0 = " and `result.x0` as x0" if name == "theta0" else ""
        raise TypeError(
            f"`{name}` is a FitResult: pass its parameters, `result.theta`{x0} (to go on "
            "from a fit, give its other arguments again, `fixed`, `constraints`, ...: the "
            "result does not keep them)."
        )
    try:
        leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    except (TypeError, ValueError) as err:
        raise ValueError(
            f"`{name}` must be a pytree that JAX can flatten (a dict's keys must sort "
            f"against each other: all str, or all int), got {_theta_summary(tree)}: {err}"
        ) from None
    for path, leaf in leaves:
        # An array of another library (a pandas Series or DataFrame) is no JAX array: JAX
        # takes it as an opaque leaf, held with the model, whose hash then failed ("`step`
        # must be hashable ... got an unhashable Series").
        if hasattr(leaf, "__array__") and not isinstance(leaf, (np.ndarray, np.generic, jax.Array)):
            where = f"`{name}{jax.tree_util.keystr(path)}`" if path else f"`{name}`"
            raise TypeError(
                f"{where} is a {type(leaf).__name__}, not a parameter JAX can take: give "
                "its values as a NumPy or JAX array (`.to_numpy()`; a pandas Series of "
                "named parameters as a dict, `series.to_dict()`)."
            )


def check_path(path, name="path", what="a file or folder", optional=True):
    """A TypeError unless `path` is a str or an `os.PathLike` (or None, where
    `optional`), a ValueError where it is the empty string."""
    if path is None and optional:
        return
    if isinstance(path, str) and path == "":
        raise ValueError(f"`{name}` is an empty string: give {what}.")
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(
            f"`{name}` must be a str or os.PathLike ({what}){' or None' if optional else ''}, "
            f"got {path!r}."
        )


def is_weak(a) -> bool:
    """Python scalars take the dtype of the arrays they meet, as in NumPy and JAX."""
    return isinstance(a, (int, float)) and not isinstance(a, bool)


def as_float(a, name, dtype=None, measured=False):
    """`a` as a floating array (JAX's canonical dtype, or `dtype`). Host data (NumPy
    arrays, lists) stay NumPy arrays, so validation costs no device transfer or eager JAX
    call; the compiled functions take them as they are. Booleans become 0 and 1, except
    for `measured` outputs (a comparison such as `z > 0` passed for z)."""
    if type(a) is np.ndarray and a.dtype == dtype and a.dtype.kind == "f":
        return a  # already what it would become (the common case of `fit`'s data)
    a = unmasked(a, name, measured)
    try:
        if isinstance(a, jax.Array):
            a = jnp.asarray(a)
        else:
            a = np.asarray(a)
            if a.dtype != object:
                a = a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False)
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{name}` must hold real numbers, got {type(a).__name__}: {err}") from err
    if a.dtype == object:
        if a.ndim == 0 and a.item() is None:
            what = (
                " (the initial state, (n_x,) or (N, n_x); np.zeros(n_x) to start at 0 where "
                "it is estimated)"
                if name == "x0"
                else " (an array of real numbers)"
            )
            raise ValueError(f"`{name}` is required{what}, got None.")
        item = a.item() if a.ndim == 0 else None
        if hasattr(item, "u") and hasattr(item, "y"):  # (a dataset's `Record`)
            raise ValueError(
                f"`{name}` must hold real numbers, got a {type(item).__name__}: pass its "
                "arrays, u = record.u and z = record.y as (T, n) columns (`[:, None]` for "
                "one channel)."
            )
        raise ValueError(f"`{name}` must hold real numbers, got dtype object.")
    if jnp.issubdtype(a.dtype, jnp.complexfloating):
        raise ValueError(f"`{name}` must hold real numbers, got dtype {a.dtype}.")
    if measured and a.dtype == jnp.bool_:
        raise ValueError(
            f"`{name}` must hold real numbers (measured outputs), got dtype bool: pass "
            f"`{name}.astype(float)` for outputs that are 0 or 1."
        )
    if name == "x0" and a.dtype == jnp.bool_:  # (the mask of `estimate_x0`, misplaced?)
        raise ValueError(
            "`x0` must hold real numbers (the initial state), got dtype bool: the entries "
            "to estimate are marked by `estimate_x0=`; pass `x0.astype(float)` for a state "
            "of 0s and 1s."
        )
    if not jnp.issubdtype(a.dtype, jnp.inexact):
        if not (jnp.issubdtype(a.dtype, jnp.integer) or a.dtype == jnp.bool_):
            raise ValueError(f"`{name}` must hold real numbers, got dtype {a.dtype}.")
        a = a.astype(jnp.result_type(float))
    if dtype is not None and a.dtype != dtype:
        a = a.astype(dtype)
    return a


def _spans_hosts(a) -> bool:
    """Whether `a` is a jax.Array with shards on other processes' devices (a fleet sharded
    over several hosts): NumPy cannot read it, a reduction on the devices can."""
    return (
        isinstance(a, jax.Array)
        and not isinstance(a, jax.core.Tracer)
        and not a.is_fully_addressable
    )


def _on_devices(a) -> bool:
    """Whether `a` is a concrete jax.Array sharded over several devices."""
    return (
        isinstance(a, jax.Array)
        and not isinstance(a, jax.core.Tracer)
        and len(a.sharding.device_set) > 1
    )


def check_state_size(x0, n_x, name="`x0`"):
    """Refuse an initial state (n_x,) or (N, n_x) of another size than a fitted state's
    n_x (the model would be blamed for it); what is not an array is left to the
    caller's checks."""
    try:
        shape = np.shape(x0)
    except ValueError:
        return
    if shape and shape[-1] != n_x:
        raise ValueError(
            f"{name} must have the fitted state's n_x = {n_x} entries (shape ({n_x},), or "
            f"(N, {n_x}) for N records), got shape {shape}."
        )


def check_finite(a, name, hint="", leaf=None):
    """A ValueError naming `name` (and, on one host, its first entry that is not finite:
    of a stack of records (N, T, n), record i's sample k) where a concrete `a` holds NaN
    or inf; `hint` follows the name. `leaf`: the name of `a` in that entry, where `a` is
    a leaf of `name` (`theta['k']`)."""
    leaf = name if leaf is None else leaf
    if isinstance(a, np.ndarray) or is_concrete(a):
        if _spans_hosts(a):
            finite, where = bool(jnp.isfinite(a).all()), ""
        else:
            bad = ~np.isfinite(np.asarray(a))
            finite = not bad.any()
            if not finite and bad.ndim:
                first = [int(i) for i in np.argwhere(bad)[0]]
                at = (
                    f"{leaf}[{first[0]}][{', '.join(map(str, first[1:]))}]"
                    if bad.ndim == 3
                    else f"{leaf}[{', '.join(map(str, first))}]"
                )
                where = f"; the first is `{at}`"
            else:
                where = f"; the first is `{leaf}`" if leaf != name else ""
        if not finite:
            raise ValueError(f"`{name}` contains NaN or inf values{hint}{where}.")


def common_dtype(*trees):
    """The floating dtype every argument is promoted to: NumPy's promotion of the arrays
    (Python scalars are weak and do not widen it), canonicalised for JAX (float32 when
    x64 is off), float32 at least: half precision (float16, bfloat16) is widened, as the
    fits' linear algebra (eigh, LAPACK) has no half-precision routines)."""
    dtypes = []
    for leaf in jax.tree_util.tree_leaves(trees):
        if is_weak(leaf) or leaf is None:
            continue
        dt = getattr(leaf, "dtype", None)
        if dt is None:
            dt = np.asarray(leaf).dtype
        if jnp.issubdtype(dt, jnp.inexact) and not jnp.issubdtype(dt, jnp.complexfloating):
            dtypes.append(dt)
    dt = np.result_type(*dtypes) if dtypes else np.result_type(float)
    if np.dtype(dt).itemsize < 4:  # float16, bfloat16: no LAPACK routine takes them
        dt = jnp.promote_types(dt, jnp.float32)
    return jax.dtypes.canonicalize_dtype(dt)


def check_theta(theta, dtype=None, name="theta"):
    """theta split into its parameters (floating arrays, the trainable leaves) and its
    static part (functions, integer and boolean arrays and other non-floating leaves, or
    None)."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    for leaf in leaves:
        if isinstance(leaf, (str, bytes, complex)) or (
            isinstance(leaf, (np.ndarray, jax.Array))
            and not (jnp.issubdtype(leaf.dtype, jnp.number) or leaf.dtype == jnp.bool_)
        ):
            raise ValueError(f"`{name}` must hold real numbers, got {leaf!r}.")
    if leaves and all(map(_pytree.is_parameter, leaves)):
        static = None  # (what `split` gives, without its copy of the tree)
    else:
        params, static = _pytree.split(theta)
        leaves, treedef = jax.tree_util.tree_flatten(params)
    leaves = [as_float(leaf, name, dtype) for leaf in leaves]
    for i, leaf in enumerate(leaves):
        try:
            check_finite(leaf, name)
        except ValueError:  # (named by its path in theta, found only then)
            params = jax.tree_util.tree_unflatten(treedef, leaves)
            path = jax.tree_util.tree_flatten_with_path(params)[0][i][0]
            check_finite(leaf, name, leaf=f"{name}{jax.tree_util.keystr(path)}")
    return jax.tree_util.tree_unflatten(treedef, leaves), static


def _check_name_counts(model, n_x, n_z):
    """The model's `states` and `outputs` names against the data's sizes."""
    for field, names, n, what in (
        ("states", model.states, n_x, "n_x"),
        ("outputs", model.outputs, n_z, "n_z"),
    ):
        if names is not None and len(names) != n:
            raise ValueError(
                f"the model's `{field}` holds {len(names)} name{'s' * (len(names) != 1)} "
                f"({list(names)}), but the data have {what} = {n}: give one name per entry "
                f"(`Model(..., {field}=...)`)."
            )


def bind_model(model, static):
    """The model seen with theta's trainable part only (static part bound in)."""
    if not isinstance(model, Model):
        raise TypeError(f"`model` must be a oneshot_jax.Model, got {type(model).__name__}.")
    if static is None:
        return model
    return Model(
        _pytree.Bound(model.step, static),
        _pytree.Bound(model.observe, static),
        input=model.input,
        timed=model.timed,
    )


def require_inputs(u) -> None:
    """A ValueError where `u` is None: a model without inputs takes u of shape (T, 0)."""
    if u is None:
        raise ValueError(
            "`u` is required, the inputs (T, n_u); a model without inputs takes "
            "np.zeros((T, 0)), which gives the record its length T."
        )


@functools.lru_cache(maxsize=256)
def _cached_eval_shape(fn, x, u, theta_leaves, treedef, x64):
    """(`x64`: JAX's jax_enable_x64 when called, part of the key: the model's own
    constants, `jnp.zeros(1)` say, take their dtype from it.)"""
    del x64
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
    return _cached_eval_shape(fn, x, u, structs, treedef, jax.config.jax_enable_x64)


@functools.lru_cache(maxsize=256)
def _cached_step_inputs(model_input, shape, dtype):
    probe = jax.ShapeDtypeStruct((2, *shape), dtype)
    out = jax.eval_shape(Model(_identity_step, input=model_input).step_inputs, probe)
    return jax.ShapeDtypeStruct(out.shape[1:], out.dtype)


def _identity_step(x, u, theta):
    return x


def _step_input_struct(model, u_1):
    """What the step sees of one input sample (`Model.step_inputs`), abstractly."""
    return _cached_step_inputs(model.input, u_1.shape, u_1.dtype)


class _Uncacheable(Exception):
    """An argument whose structural checks cannot be keyed (a ragged list, an integer
    array in theta, which is bound into the model by value, an unhashable leaf)."""


def _array_signature(a):
    """What the structural checks see of one array argument: its kind, shape and dtype."""
    if a is None:
        return None
    if isinstance(a, (np.ndarray, jax.Array)):
        return (isinstance(a, np.ndarray), a.shape, a.dtype, getattr(a, "weak_type", False))
    raise _Uncacheable


def _theta_signature(theta):
    """theta's structure, each parameter leaf's kind, shape and dtype, and its static
    leaves themselves (they are bound into the model)."""
    leaves, treedef = jax.tree_util.tree_flatten(theta)
    sig = [treedef]
    for leaf in leaves:
        if isinstance(leaf, (np.ndarray, jax.Array, np.generic)):
            if not jnp.issubdtype(leaf.dtype, jnp.inexact):
                raise _Uncacheable  # data bound in by value (or a wrong dtype: the checks say)
            if isinstance(leaf, np.generic):
                sig.append((np.generic, leaf.dtype))
            else:
                sig.append(_array_signature(leaf))
        elif is_weak(leaf):
            sig.append(type(leaf))
        else:
            try:
                hash(leaf)
            except TypeError:
                raise _Uncacheable from None
            sig.append(("static", type(leaf), leaf))
    return tuple(sig)


def _signature(model, theta, x0, u, z, weight, missing):
    """A key for the structural results of `check_data` (the dtype, the model with theta's
    static part bound in, the abstract output), or None where there is none."""
    try:
        key = (
            id(model),  # (hashing a model walks all of it; the entry keeps it alive)
            _theta_signature(theta),
            _array_signature(x0),
            _array_signature(u),
            _array_signature(z),
            _array_signature(weight),
            missing,
            jax.config.jax_enable_x64,  # the canonical dtypes depend on it
        )
        hash(key)
    except (_Uncacheable, TypeError):  # TypeError: an unhashable model
        return None
    return key


# check_data's structural results by `_signature`: (the given model, dtype, the bound
# model, z_hat). Bounded, so that models made anew in a loop do not accumulate.
_STRUCTURE: dict = {}
_STRUCTURE_MAX = 256


def _remember(key, value):
    if key is None:
        return
    if len(_STRUCTURE) >= _STRUCTURE_MAX:
        _STRUCTURE.pop(next(iter(_STRUCTURE)))
    _STRUCTURE[key] = value


class Data(NamedTuple):
    """Validated arguments: theta's trainable part, the model with theta's static part
    bound in, and the data, all in one floating dtype."""

    model: Any
    theta: Any
    static: Any
    x0: Any
    u: Any
    z: Any
    weight: Any
    batched: bool
    n_z: int
    mask: Any = None  # a `Mask` (padding of ragged trajectories, missing outputs) or None
    lengths: Any = None  # each trajectory's length when they were given as ragged lists


def _given_dtype(a):
    """The dtype `a` holds as given (an array's, or NumPy's reading of a list or a
    number); object where it has none."""
    dtype = getattr(a, "dtype", None)
    if dtype is None:
        try:
            dtype = np.asarray(a).dtype
        except (TypeError, ValueError):
            return np.dtype(object)
    return np.dtype(dtype)


def check_weight(weight, n_z, dtype):
    """`weight` as a (n_z,) vector (diagonal Q) or an (n_z, n_z) PSD matrix (a scalar for
    one output, as a (1,) vector); None stays None."""
    if weight is None:
        return None
    w = as_float(weight, "weight", dtype)
    if _given_dtype(weight) == np.bool_:  # (as_float takes booleans as 0 and 1)
        raise TypeError(f"`weight` must hold numbers (Q of eq. 4), got the boolean {weight!r}.")
    if w.ndim == 0:
        # (its sign first: a wrong shape would hide it)
        check_finite(w, "weight")
        if is_concrete(w) and float(w) < 0:
            raise ValueError(f"`weight` (Q of eq. 4) must be non-negative, got {float(w):g}.")
        if n_z != 1:
            raise ValueError(
                "`weight` is a scalar, which is taken for one output only: the model has "
                f"n_z = {n_z} outputs, and a scalar would weigh them all alike (the estimates "
                f"of no weight); give one weight per output, shape ({n_z},) (a diagonal Q), "
                f"or a ({n_z}, {n_z}) PSD matrix Q."
            )
        w = w.reshape(1)
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
                bad = ", ".join(f"weight[{i}] = {wn[i]:g}" for i in np.flatnonzero(wn < 0)[:8])
                raise ValueError(f"`weight` (diagonal of Q) must be non-negative, got {bad}.")
        else:
            if not np.allclose(wn, wn.T, rtol=1e-10, atol=1e-12 * scale):
                raise ValueError("`weight` must be a symmetric matrix Q.")
            if np.min(np.linalg.eigvalsh(wn)) < -1e-10 * scale:
                raise ValueError("`weight` must be positive semi-definite (Q >= 0, eq. 4).")
        if not np.any(wn):
            raise ValueError(
                "`weight` is all zeros: Q = 0 weighs every output error by zero, so the "
                "data carry no information; give a non-zero Q (None for the identity)."
            )
    return w


def check_outside_transformations(*args, name=None):
    """`fit` and the helpers built on it run their own compiled call on concrete data;
    `name` (e.g. "`estimate_x0`") for a function other than `fit`."""
    if is_concrete(*args):
        return
    if name is not None:
        raise TypeError(
            f"{name} runs outside JAX transformations (jit, vmap, grad): it was given "
            "traced values. It solves for x0 on the host; to transform a simulation, the "
            "loss or its gradient use `oneshot_jax.simulate` / `oneshot_jax.loss` / "
            "`oneshot_jax.value_and_grad`, which work under jit, vmap and grad."
        )
    raise TypeError(
        "`fit` runs outside JAX transformations (jit, vmap, grad): it was given traced "
        "values. It compiles its own solve; to fit several data sets at once use "
        "several trajectories (x0 (N, n_x), u (N, T, n_u)) or `multistart=True`, and "
        "to transform the loss or its gradient use `oneshot_jax.loss` / "
        "`oneshot_jax.value_and_grad` / `oneshot_jax.simulate`, which work under jit, "
        "vmap and grad."
    )


def _checked_trajectories(items, name, dtype, n_traj, measured=False):
    """Ragged trajectories checked (one per row of x0, each (T_i, c) with T_i >= 1, the
    same c), as float arrays of `dtype`; `_normalise.pad` stacks them."""
    if len(items) != n_traj:
        raise ValueError(
            f"`{name}` holds {len(items)} trajectories but `x0` has {n_traj} rows (N, n_x)."
        )
    arrays = [as_float(a, f"{name}[{i}]", dtype, measured) for i, a in enumerate(items)]
    for i, a in enumerate(arrays):
        if a.ndim != 2 or a.shape[0] < 1:
            raise ValueError(
                f"`{name}[{i}]` must have shape (T_{i}, {'n_u' if name == 'u' else 'n_z'}) "
                f"with T_{i} >= 1, got shape {a.shape}."
            )
        if a.shape[1] != arrays[0].shape[1]:
            raise ValueError(
                f"`{name}[{i}]` has {a.shape[1]} channels but `{name}[0]` has {arrays[0].shape[1]}."
            )
    return arrays


def _theta_summary(theta, limit=200):
    """A short description of theta's structure: its type, and its leaves' shapes."""

    def describe(a):
        if isinstance(a, eqx.Module):  # (a network inside theta: its size, not its repr)
            arrays = jax.tree_util.tree_leaves(eqx.filter(a, eqx.is_array))
            return f"{type(a).__name__} of {sum(x.size for x in arrays)} numbers"
        return getattr(a, "shape", type(a).__name__)

    try:
        shapes = jax.tree_util.tree_map(
            describe, theta, is_leaf=lambda a: isinstance(a, eqx.Module) and a is not theta
        )
        text = f"a {type(theta).__name__}, leaf shapes {shapes}"
    except Exception:  # noqa: BLE001 - a description only
        text = f"a {type(theta).__name__}"
    return text if len(text) <= limit else text[: limit - 3] + "..."


@contextlib.contextmanager
def _naming_shapes(what, x_1, u_1, x0, u, theta, theta_name):
    """Re-raise an error of tracing `what` as a ValueError with the arguments' shapes; an
    exception of the user's own class (not Python's or JAX's) is re-raised as itself, with
    the shapes added as a note, so that `except MyError:` around `fit` catches it wherever
    the model raises it."""
    try:
        yield
    except Exception as err:  # noqa: BLE001 - re-raised with the arguments' shapes
        text = (
            f"calling {what} on a state of shape {x_1.shape} (from `x0` of shape {x0.shape}), "
            f"an input of shape {u_1.shape} (from `u` of shape {u.shape}) and the "
            f"parameters `{theta_name}` ({_theta_summary(theta)}) failed"
        )
        module = type(err).__module__.split(".")[0]
        if module not in ("builtins", "jax", "jaxlib", "equinox", "numpy", "oneshot_jax"):
            err.add_note(text)
            raise
        raise ValueError(f"{text}: {type(err).__name__}: {err}") from err


def _broadcast(*shapes):
    """The shape the shapes broadcast to, or None where they do not."""
    try:
        return np.broadcast_shapes(*shapes)
    except ValueError:
        return None


def _check_rhs(rhs, x_1, u_1, theta, x0, u, theta_name, shown):
    """`Model.from_ode`'s `rhs` traced once on abstract values: it must return dx/dt of
    the state's shape."""
    with _naming_shapes("the model's `rhs` (`Model.from_ode`)", x_1, u_1, x0, u, shown, theta_name):
        dx = _abstract_call(rhs, x_1, u_1, theta)
    if not isinstance(dx, jax.ShapeDtypeStruct) or dx.shape != x_1.shape:
        hint = ""
        if isinstance(dx, (list, tuple)):
            got = f"a {type(dx).__name__} (build dx/dt with jnp.stack or jnp.array)"
        else:
            got = getattr(dx, "shape", type(dx).__name__)
            if u_1.shape != x_1.shape and got == _broadcast(x_1.shape, u_1.shape):
                hint = (
                    f" (it has the shape of an input u[k], {u_1.shape}, from `u` of shape "
                    f"{u.shape}: does `u` have the columns the model reads?)"
                )
            elif isinstance(got, tuple) and len(got) == len(x_1.shape) == 1 and got > x_1.shape:
                hint = (
                    f" (if the model has {got[0]} states, x0 needs all {got[0]}, the "
                    "unmeasured ones too: e.g. np.r_[z[0], 0.0] for a measured position "
                    "and a velocity started at 0, estimated by `fit`)"
                )
        raise ValueError(
            f"the model's `rhs` (`Model.from_ode`) must return dx/dt as an array of shape "
            f"{x_1.shape} (the shape of x0), got {got}: `rhs` and `x0` (of shape "
            f"{x0.shape}) must agree on the number of states{hint}."
        )
    if dx.dtype != x_1.dtype:
        raise ValueError(
            f"the model's `rhs` (`Model.from_ode`) must return dx/dt in the state's dtype "
            f"{x_1.dtype} (the dtype of the data), got {dx.dtype}: an array or constant of "
            "another dtype inside `rhs` (jnp.float32(...), dtype=...) changes it; the "
            "integrator would carry the state in the wrong precision."
        )


def _check_indices(model, theta, x_1, u_step, u_seen, n_u):
    """A model that indexes past the end of an array (u[1] of a single input, x[2] of a
    two-state x0, an entry beyond a parameter's shape) runs without an error in JAX,
    which clamps the index (u[1] reads u[0]): the fit would run on a wrong model. The
    constant indices of the step and the observation are checked on their jaxpr
    (`_indices.out_of_range`: no program compiled)."""

    def both(x, us, ue, th):
        return model.step(x, us, th), model.observe(x, ue, th)

    found = out_of_range(both, x_1, u_step, u_seen, theta)
    if found:
        shape, axis, index = found[0]
        raise ValueError(
            f"the model indexes past the end of an array: index {index} on axis {axis} of "
            f"an array of shape {shape}. JAX clamps such an index instead of raising (u[1] "
            "of a single input reads u[0]), so the model would run wrong silently. Check "
            f"the columns of `u` (n_u = {n_u}), the size of the state (n_x = "
            f"{x_1.shape[0]}, from `x0`) and the shapes of theta's parameters against what "
            "the model reads."
        )


def _warn_if_transposed(model, theta, x0, u, lead):
    """Warn where `u` holds one sample of n_u > 1 inputs of which the model reads only the
    first (its step and observation unchanged when the others change): a one-input
    record of n_u samples given transposed, (1, T). Without z nothing else can tell (a
    one-sample simulation is valid); evaluated on the values, concrete ones only."""
    if not is_concrete(theta, x0, u):
        return
    first = (0,) * len(lead)
    x, u_k = jnp.asarray(x0[first]), jnp.asarray(u[first][0])
    other = u_k.at[1:].add(1.0 + jnp.abs(u_k[1:]))  # (every input but the first moved)

    def seen(u_k):
        u_step = jnp.stack([u_k, u_k]) if model.input == "foh" else u_k
        return model.step(x, u_step, theta), model.observe(x, u_k, theta)

    try:
        same = all(
            bool(jnp.array_equal(a, b))
            for a, b in zip(jax.tree.leaves(seen(u_k)), jax.tree.leaves(seen(other)))
        )
    except Exception:  # (the model's own errors are reported where it runs)
        return
    if same:
        n = u_k.shape[0]
        level = 2 + frames_to_user()  # (at the user's line, whichever function checks)
        warn(
            f"`u` has shape {u.shape}: one sample of {n} inputs, and the model reads only "
            f"the first input. Is it transposed? A one-input record of {n} samples is u "
            f"of shape ({n}, 1) (u.T); u is (T, n_u).",
            stacklevel=level,
        )


def _check_model(model, theta, x0, u, lead, dtype, theta_name="theta", shown=None):
    """Trace the user's functions once on abstract values, so that a step that changes the
    state's shape or dtype is reported here and not as an error deep inside a scan.
    Returns the model (its observation promoted to `dtype` where it returns integers) and
    the abstract output z. `shown`: the theta that the errors describe (default `theta`,
    whose held leaves are None)."""
    shown = theta if shown is None else shown
    x_1 = jax.ShapeDtypeStruct(x0.shape[len(lead) :], x0.dtype)
    u_1 = jax.ShapeDtypeStruct(u.shape[len(lead) + 1 :], u.dtype)
    u_seen = u_1  # a timed model's functions see the interval appended (`_timing`)
    if model.timed:
        u_seen = jax.ShapeDtypeStruct((u_1.shape[0] + 1,), u_1.dtype)
    u_step = _step_input_struct(model, u_seen)
    if isinstance(model.step, ODE_STEPS):
        # RK4 broadcasts dx/dt against x: a right-hand side of the wrong shape would give
        # a state of the right shape and a wrong model.
        _check_rhs(model.step.rhs, x_1, u_1, theta, x0, u, theta_name, shown)
    with _naming_shapes("the model's `step`", x_1, u_1, x0, u, shown, theta_name):
        x_next = _abstract_call(model.step, x_1, u_step, theta)
    with _naming_shapes("the model's `observe`", x_1, u_1, x0, u, shown, theta_name):
        z_hat = _abstract_call(model.observe, x_1, u_seen, theta)
    _check_indices(model, theta, x_1, u_step, u_seen, u_1.shape[0])
    if not isinstance(x_next, jax.ShapeDtypeStruct) or x_next.shape != x_1.shape:
        shape = str(getattr(x_next, "shape", type(x_next).__name__))
        if isinstance(x_next, (list, tuple)):
            shape += " (build the state with jnp.stack or jnp.array)"
        if u.shape[-1] > u.shape[-2]:  # more inputs than samples: (n_u, T) given
            shape += (
                f"; `u` of shape {u.shape} holds T = {u.shape[-2]} samples of {u.shape[-1]} "
                "inputs: is it transposed? (u is (T, n_u))"
            )
        raise ValueError(
            f"`model.step` must return a state of shape {x_1.shape} (the shape of x0), got {shape}."
        )
    if x_next.dtype != x_1.dtype:
        raise ValueError(
            f"`model.step` must keep the state's dtype {x_1.dtype} (the dtype of x0), "
            f"got {x_next.dtype}."
        )
    if not isinstance(z_hat, jax.ShapeDtypeStruct) or z_hat.ndim != 1:
        shape = getattr(z_hat, "shape", type(z_hat).__name__)
        if isinstance(z_hat, (list, tuple)):
            shape += " (build z with jnp.stack or jnp.array)"
        raise ValueError(
            f"`model.observe` must return a 1-D output z of shape (n_z,), got {shape}."
        )
    if z_hat.shape[0] == 0:  # (a slice past the state's end, x[2:3] of 2 states, is empty)
        raise ValueError(
            f"`model.observe` returned no output (shape (0,)) for a state of shape "
            f"{x_1.shape}: a slice past the state's end (such as x[{x_1.shape[0]}:"
            f"{x_1.shape[0] + 1}]) is empty; it must return at least one output."
        )
    if not jnp.issubdtype(z_hat.dtype, jnp.inexact):  # outputs are real numbers
        model = Model(
            model.step, FloatObserve(model.observe, dtype), input=model.input, timed=model.timed
        )
        z_hat = jax.ShapeDtypeStruct(z_hat.shape, dtype)
    elif z_hat.dtype != dtype:
        # z is compared in z_hat's dtype: another precision than the data's would round
        # the measurements (float32) or mix precisions (float64 outputs of float32 data).
        raise ValueError(
            f"`model.observe` must return z in the data's dtype {dtype}, got {z_hat.dtype}: "
            "an array or constant of another dtype inside `observe` (jnp.float32(...), "
            "dtype=...) changes it."
        )
    return model, z_hat


def _transposed_hint(z_shape, u_shape, T, n_z, z_name):
    """Which of a record's arrays looks given as (columns, T) rather than (T, columns)."""
    if len(z_shape) < 2:
        return ""
    # u given as (n_u, T): its T samples read as inputs, more of them than samples
    u_flipped = u_shape[-1] > T and u_shape[-1] in z_shape[-2:]
    z_flipped = z_shape[-1] == (u_shape[-1] if u_flipped else T) and z_shape[-1] != z_shape[-2]
    if u_flipped and z_flipped:
        return (
            f"; `u` of shape {u_shape} and `{z_name}` hold {u_shape[-1]} along their last "
            f"axis: are both transposed? (u is (T, n_u), {z_name} is (T, n_z))"
        )
    if u_flipped or (n_z is not None and z_shape[-2] == u_shape[-1] != T and z_shape[-1] == n_z):
        return (
            f"; `u` of shape {u_shape} holds T = {T} samples of {u_shape[-1]} "
            "inputs: is it transposed? (u is (T, n_u))"
        )
    if z_flipped:
        return f": is `{z_name}` transposed? ({z_name} is (T, n_z))"
    return ""


def _size_hint(z_shape, want, model, z_name):
    """Which argument a `z` of the wrong shape (not transposed) disagrees with: `u`'s
    number of samples, or, for a model that observes its whole state, `x0`'s size."""
    if len(z_shape) != len(want):
        return ""
    if z_shape[-2] != want[-2] and z_shape[-1] == want[-1]:
        return (
            f" (`u` holds T = {want[-2]} samples and `{z_name}` {z_shape[-2]}: a record's "
            "inputs and outputs are sampled together)"
        )
    if z_shape[:-1] == want[:-1] and getattr(model, "observes_state", False):
        return (
            f" (the model observes its whole state, as no `observe` was given: n_z is the "
            f"size of `x0`, {want[-1]}; is `x0` of the right size?)"
        )
    return ""


def check_data(
    model,
    theta,
    x0,
    u,
    z=None,
    weight=None,
    missing="raise",
    t=None,
    readings=False,
    *,
    theta_name="theta",
    z_name="z",
) -> Data:
    """Validate (theta, x0, u, z, weight) for `model` and return them canonicalised.

    Single trajectory: x0 (n_x,), u (T, n_u), z (T, n_z). Several trajectories sharing
    theta (the paper's footnote 1): x0 (N, n_x), u (N, T, n_u), z (N, T, n_z), or `u` and
    `z` as lists of N arrays of different lengths T_i (padded to the longest and masked).
    Every array is promoted to one floating dtype, as NumPy would promote them.
    `missing="mask"` takes NaN entries of z as missing samples (masked); with "raise"
    (default) they are an error. `t`, the sample times of a timed model's records
    (`_timing.check_times`), becomes the intervals appended to u as its last column.
    `readings`: aggregated readings (`_aggregate`) come with z, so a z without any point
    sample is not refused here (the augmented data are checked again). `theta_name`,
    `z_name`: the caller's names of theta and z, for the errors (`theta0`, `z_head`).
    """
    if missing not in ("raise", "mask"):
        raise ValueError(f"`missing` must be 'raise' or 'mask', got {missing!r}.")
    check_tree(theta, theta_name)
    # What depends only on the model, the structure, shapes and dtypes of the arguments
    # (the dtype, the bound model, the abstract trace below) is kept from an earlier call
    # that passed the checks; the checks of values run every time.
    key = _signature(model, theta, x0, u, z, weight, missing)
    known = _STRUCTURE.get(key) if key is not None else None
    if known is not None and known[0] is not model:  # an id reused by a new object
        known = None
    ragged = is_ragged(u) or (z is not None and is_ragged(z))
    if known is None:
        rows_u = list(u) if ragged and isinstance(u, (list, tuple)) else [u]
        rows_z = list(z) if ragged and isinstance(z, (list, tuple)) else [z]
        dtype = common_dtype(_pytree.split(theta)[0], x0, *rows_u, *rows_z)
    else:
        _, dtype, bound, z_hat = known
    shown = theta  # (the errors describe the whole theta, its held integer leaves too)
    theta, static = check_theta(theta, dtype, theta_name)
    given = model
    model = bind_model(model, static) if known is None else bound
    x0 = as_float(x0, "x0", dtype)
    if x0.ndim not in (1, 2):
        raise ValueError(
            "`x0` must have shape (n_x,) for one trajectory or (N, n_x) for N "
            f"trajectories, got shape {x0.shape}."
        )
    batched = x0.ndim == 2
    lengths = None
    if ragged:
        if not batched:
            raise ValueError(
                "`u` and `z` given as lists of trajectories of different lengths need `x0` "
                f"of shape (N, n_x), one row per trajectory; got shape {x0.shape}."
            )
        if not (isinstance(u, (list, tuple)) and (z is None or isinstance(z, (list, tuple)))):
            raise ValueError(
                "trajectories of different lengths: give both `u` and `z` as lists of "
                "per-trajectory arrays."
            )
        if z is not None and len(u) != len(z):
            raise ValueError(
                f"`u` holds {len(u)} trajectories but `{z_name}` holds {len(z)}: one output "
                "record per input record."
            )
        u, lengths = pad(_checked_trajectories(u, "u", dtype, x0.shape[0]), dtype)
        if z is not None:
            z_padded, z_lengths = pad(
                _checked_trajectories(z, z_name, dtype, x0.shape[0], measured=True), dtype
            )
            for i, (a, b) in enumerate(zip(lengths, z_lengths)):
                if a != b:
                    raise ValueError(
                        f"`z[{i}]` has {b} samples but `u[{i}]` has {a}: each trajectory "
                        "needs one output sample per input sample."
                    )
            z = z_padded
    require_inputs(u)
    u = as_float(u, "u", dtype)
    lead = x0.shape[:1] if batched else ()
    if u.ndim != len(lead) + 2 or u.shape[: len(lead)] != lead:
        want = f"({x0.shape[0]}, T, n_u)" if batched else "(T, n_u)"
        hint = ""
        if not batched and u.ndim == 3:
            hint = (
                f": for {u.shape[0]} records give one initial state per record, x0 of shape "
                f"({u.shape[0]}, {x0.shape[0]}) (np.tile(x0, ({u.shape[0]}, 1)))"
            )
        elif u.ndim == 1 and u.shape[0] > 1:
            hint = ": a one-input record of T samples is u[:, None], shape (T, 1)"
        if batched and x0.shape[1] == 1 and u.ndim == 2:
            hint = (
                f": `x0` of shape {x0.shape} is read as {x0.shape[0]} trajectories of one "
                f"state; for one trajectory of {x0.shape[0]} states give x0 of shape "
                f"({x0.shape[0]},) (np.ravel(x0))"
            )
        elif batched and u.ndim == 2:
            first = " (x0[0])" if x0.shape[0] == 1 else ""
            many = "one trajectory" if x0.shape[0] == 1 else f"{x0.shape[0]} trajectories"
            hint = (
                f": `x0` of shape {x0.shape} holds one initial state per trajectory "
                f"({many} of {x0.shape[1]} states); for the one record "
                f"`u` of shape (T, n_u) give x0 of shape ({x0.shape[1]},){first}"
            )
        raise ValueError(
            f"`u` must have shape {want} to match `x0` of shape {x0.shape}, got shape "
            f"{u.shape}{hint}."
        )
    T, u_shape = u.shape[-2], u.shape
    if T < 1:
        raise ValueError(f"`u` must hold at least one sample (T >= 1), got shape {u.shape}.")
    if batched and x0.shape[0] < 1:
        raise ValueError("`x0` must hold at least one trajectory (N >= 1).")
    check_finite(x0, "x0")
    check_finite(
        u,
        "u",
        ""
        if missing == "raise"
        else " (`missing='mask'` applies to z: the inputs drive "
        "the model at every sample; fill the gaps of u, e.g. by interpolation)",
    )
    intervals = check_times(model, t, u.shape[:-1], lengths, dtype, given.step)

    if z is not None and not ragged:
        # The samples of z must match u's before the model is traced: a record given
        # transposed, (n_u, T), would otherwise surface as a wrong state shape in the
        # model (a step that broadcasts b * u), not as the data error it is.
        z_shape = np.shape(z)
        hint = ""
        if len(z_shape) == len(lead) + 2 and z_shape[:-1] != (*lead, T):
            hint = _transposed_hint(z_shape, u_shape, T, None, z_name)
        if hint:
            raise ValueError(
                f"`{z_name}` must have shape ({', '.join(map(str, (*lead, T)))}, n_z) (the "
                f"leading axes of `u`: T = {T} samples), got shape {z_shape}{hint}."
            )
    if known is None:
        model, z_hat = _check_model(model, theta, x0, u, lead, dtype, theta_name, shown)
    if T == 1 and u_shape[-1] > 1 and z is None and not model.timed:
        _warn_if_transposed(model, theta, x0, u, lead)
    n_z = z_hat.shape[0]
    _check_name_counts(given, x0.shape[-1], n_z)
    u = append_intervals(u, intervals)

    mask = None
    if z is not None:
        z = as_float(z, z_name, z_hat.dtype, measured=True)
        want = (*lead, T, n_z)
        if z.shape != want:
            hint = _transposed_hint(z.shape, u_shape, T, n_z, z_name) or _size_hint(
                z.shape, want, model, z_name
            )
            raise ValueError(
                f"`{z_name}` must have shape {want} (leading axes of `u`, n_z = {n_z} outputs of "
                f"`model.observe`), got shape {z.shape}{hint}."
            )
        observed = None
        if missing == "mask" and is_concrete(z) and _on_devices(z):
            # A fleet sharded over devices (`oneshot_jax.sharding`): masked where it lies.
            observed = ~jnp.isnan(z)
            if bool(jnp.isinf(z).any()):
                raise ValueError(f"`{z_name}` contains inf values (NaN marks a missing sample).")
            if not bool(observed.any()) and not readings:
                raise ValueError(f"`{z_name}` is NaN everywhere: no output sample is measured.")
            if (
                batched
                and not readings
                and not bool(observed.reshape(z.shape[0], -1).any(axis=1).all())
            ):
                raise ValueError(
                    f"`{z_name}`: a trajectory (first axis) has no measured sample (NaN "
                    "everywhere): leave it out."
                )
            z = jnp.where(observed, z, jnp.zeros((), z.dtype))
        elif missing == "mask" and is_concrete(z):
            zn = np.asarray(z)
            if np.any(np.isinf(zn)):
                raise ValueError(f"`{z_name}` contains inf values (NaN marks a missing sample).")
            z, observed = fill_missing(zn)
            if not observed.any() and not readings:  # (readings: aggregates measure it)
                raise ValueError(
                    f"`{z_name}` is NaN everywhere (in every sample given): no output sample "
                    "is measured."
                )
            if batched and not readings:
                empty = np.flatnonzero(~observed.reshape(observed.shape[0], -1).any(axis=1))
                if empty.size:
                    raise ValueError(
                        f"`{z_name}`: trajectory {empty.tolist()} (first axis) has no measured "
                        "sample (NaN everywhere): leave it out."
                    )
        elif missing == "mask":  # traced z (under jax.jit or vmap): mask its NaN in the trace
            observed = ~jnp.isnan(z)
            z = jnp.where(observed, z, jnp.zeros((), z.dtype))
        else:
            check_finite(
                z,
                z_name,
                " (`fit`, `loss`, `value_and_grad`, `estimate_x0` and `predict` take "
                '`missing="mask"`, which treats NaN as a missing sample)',
            )
        if is_concrete(z) and z.size:
            _check_magnitude(z if _spans_hosts(z) else np.asarray(z), z_name)
        mask = sample_mask(z.shape, z.dtype, lengths, observed)
    weight = check_weight(weight, n_z, z_hat.dtype)
    if known is None:
        _remember(key, (given, dtype, model, z_hat))
    return Data(model, theta, static, x0, u, z, weight, batched, n_z, mask, lengths)


def _check_magnitude(z: np.ndarray, name: str = "z") -> None:
    """Refuse outputs whose squares underflow in their dtype: the loss would be exactly
    zero (a fit then ends at its start, `zero_residual`)."""
    largest = float(jnp.max(jnp.abs(z))) if _spans_hosts(z) else np.max(np.abs(z))
    if 0 < largest and np.square(largest) < np.finfo(z.dtype).tiny:
        raise ValueError(
            f"`{name}`: its largest magnitude {largest:.3g} squares to below the smallest normal "
            f"{z.dtype} number ({np.finfo(z.dtype).tiny:.3g}), so the loss cannot see the "
            "outputs: rescale them (to units where they are of order 1)."
        )


def check_cost(data: Data, penalty, penalty_weight) -> Cost:
    """The `Cost` of validated data: the weight, and the penalty with its multiplier
    lambda as an array in the data's dtype (a penalty must return a scalar)."""
    if penalty is not None and not callable(penalty):
        raise ValueError(f"`penalty` must be callable h(x, theta) -> scalar, got {penalty!r}.")
    dtype = data.x0.dtype
    if penalty is None:
        return _pytree.build(
            Cost, weight=data.weight, penalty=None, penalty_weight=np.zeros((), dtype)
        )
    pw = penalty_weight
    msg = f"`penalty_weight` must be a finite real scalar, got {penalty_weight!r}."
    try:
        ok = np.ndim(pw) == 0 and not np.iscomplexobj(pw) and not isinstance(pw, str)
        # (a bool is no weight: True ran as lambda = 1)
        ok = ok and not isinstance(pw, (bool, np.bool_)) and np.asarray(pw).dtype != bool
        ok = ok and (not is_concrete(pw) or bool(np.isfinite(float(pw))))
    except (TypeError, ValueError) as err:
        raise ValueError(msg) from err
    if not ok:
        raise ValueError(msg)
    if data.static is not None:
        penalty = _pytree.BoundPenalty(penalty, data.static)
    x = data.x0[0] if data.batched else data.x0
    try:
        out = jax.eval_shape(penalty, x, data.theta)
    except Exception as err:  # noqa: BLE001 - re-raised with the arguments' shapes
        raise ValueError(
            f"calling `penalty` on a state of shape {x.shape} failed: {type(err).__name__}: {err}"
        ) from err
    if getattr(out, "shape", None) != ():
        raise ValueError(
            f"`penalty` must return a scalar h(x, theta), got shape {getattr(out, 'shape', out)}."
        )
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise ValueError(
            f"`penalty` must return a floating scalar h(x, theta) (differentiable in x and "
            f"theta), got dtype {out.dtype}."
        )
    pw = jnp.asarray(pw, dtype) if not is_concrete(pw) else np.asarray(pw, dtype)
    return Cost(data.weight, penalty, pw)


def _named_free(fixed, theta):
    """`fixed` with the keys of theta's dicts that it does not name set to False (free)."""
    if not (isinstance(fixed, dict) and isinstance(theta, dict)):
        return fixed
    fixed = _pytree.nest_dotted(fixed, theta, "fixed")
    unknown = sorted(set(fixed) - set(theta), key=str)
    if unknown:
        raise ValueError(
            f"`fixed` names parameters that are not in theta0: {unknown}; theta0 has "
            f"{sorted(theta, key=str)}."
        )
    return {k: _named_free(fixed[k], v) if k in fixed else False for k, v in theta.items()}


def _lists_as_masks(fixed, theta):
    """`fixed` with a list (or tuple) where theta has an array leaf read as a NumPy array:
    the MATLAB-style mask `[True, False, False]` of an array theta (or of an array in a
    dict of theta), which JAX would take for a pytree of three leaves."""
    if isinstance(fixed, dict) and isinstance(theta, dict):
        return {k: _lists_as_masks(v, theta[k]) if k in theta else v for k, v in fixed.items()}
    if isinstance(fixed, (list, tuple)) and theta is not None and _is_leaf(theta):
        try:
            return np.asarray(fixed)
        except ValueError:  # (ragged lists: the structure's own message)
            return fixed
    return fixed


def _is_leaf(theta) -> bool:
    return jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(theta))


def _array_mask_hint(theta) -> str:
    """What to give as `fixed` for an array theta0."""
    shape = np.shape(theta)
    hint = f"a boolean array of theta0's shape {shape} (True where held)"
    if len(shape) == 1 and shape[0] <= 6:
        hint += f", e.g. np.array({[i == 0 for i in range(shape[0])]})"
    return hint


def _held_names(fixed, theta):
    """The names `fixed` gives of the parameters it holds ("k", or ["k", "phys.c"], as
    MATLAB's `nlgreyest` users name them; for an equinox module theta also a dict from its
    fields' names to single booleans, the True ones), or None where `fixed` is a pytree of
    booleans."""
    if isinstance(fixed, str):
        return [fixed]
    if isinstance(fixed, (list, tuple, set, frozenset)):
        names = list(fixed)
        if not names:  # (no names: nothing held, where theta has names)
            return names if isinstance(theta, dict) or _is_module(theta) else None
        if all(isinstance(n, str) for n in names):
            return names
        if any(isinstance(n, str) for n in names):
            raise TypeError(
                f"`fixed` mixes names and other entries: {sorted(map(repr, names))}; give "
                "the names of the parameters to hold (['k', 'c']), or a pytree of "
                "booleans shaped like theta0."
            )
        return None
    flat = _dotted_booleans(fixed)
    if flat is not None and (isinstance(theta, dict) or _is_module(theta)):
        # (a dict of single booleans, nested or by dotted names: the True ones are held,
        # each name checked against theta's, into an equinox module's fields too)
        _pytree.named_mask(list(flat), theta, "fixed")
        return [k for k, v in flat.items() if v]
    return None


def _dotted_booleans(fixed, prefix=""):
    """A dict of single booleans (nested dicts of them too) as {dotted name: bool}, or
    None where `fixed` is no such dict (an array mask inside, say)."""
    if not isinstance(fixed, dict) or not fixed:
        return None
    out = {}
    for key, value in fixed.items():
        name = f"{prefix}{key}"
        if isinstance(value, (bool, np.bool_)):
            inner = {name: bool(value)}
        else:
            inner = _dotted_booleans(value, f"{name}.")
            if inner is None:
                return None
        if set(inner) & set(out):
            raise ValueError("`fixed` names a parameter twice (dotted and nested).")
        out.update(inner)
    return out


def _is_module(theta) -> bool:
    import equinox as eqx

    return isinstance(theta, eqx.Module)


def fixed_mask(fixed, theta) -> np.ndarray:
    """Flat boolean mask of the fixed entries of theta's parameters (leaf order).

    `fixed` is a pytree of booleans with the structure of theta, or a prefix of it: a
    boolean where theta has a subtree (an equinox module, a dict) fixes or frees the whole
    subtree; an array of booleans where theta has an array leaf fixes it per entry. Where
    theta has a dict, `fixed` may name some of its keys: the others are free; it may also
    be a name or a list of names of them (each held whole), as it may for the fields of
    an equinox module theta (or a dict from their names to booleans). A list of booleans
    where theta has an array leaf is that leaf's mask (`_lists_as_masks`).
    """
    n = sum(int(np.size(leaf)) for leaf in jax.tree_util.tree_leaves(theta))
    if fixed is None:
        return np.zeros(n, bool)
    if isinstance(fixed, (bool, np.bool_)):
        return np.full(n, bool(fixed))
    names = _held_names(fixed, theta)
    if names is not None:
        if not (isinstance(theta, dict) or _is_module(theta)):
            what = (
                _array_mask_hint(theta)
                if _is_leaf(theta)
                else "a pytree of booleans shaped like theta0"
            )
            raise ValueError(
                f"`fixed` names parameters ({names}), but theta0 is a "
                f"{type(theta).__name__}, not a dict or an equinox module: give {what} "
                "instead."
            )
        return _pytree.named_mask(names, theta, "fixed")
    fixed = _lists_as_masks(_named_free(fixed, theta), theta)
    leaves, treedef = jax.tree_util.tree_flatten(fixed)
    try:
        subtrees = treedef.flatten_up_to(theta)
    except (ValueError, TypeError) as err:
        if _is_leaf(theta):  # (an array theta: no pytree to speak of)
            raise ValueError(
                f"`fixed` must be a boolean, or {_array_mask_hint(theta)}; got "
                f"{type(fixed).__name__}."
            ) from err
        raise ValueError(
            "`fixed` must be a pytree of booleans with the structure of theta0 (or a prefix "
            f"of it: one boolean for a whole subtree); theta0 has "
            f"{jax.tree_util.tree_structure(theta)}, got {treedef}."
        ) from err
    parts = []
    for f, sub in zip(leaves, subtrees):
        f = np.asarray(f)
        if f.dtype != bool:
            raise ValueError(
                f"`fixed` entries must be booleans (True where held), got dtype {f.dtype}"
                + (f": {f.tolist()}" if f.size <= 8 else "")
                + "."
            )
        sub_leaves = jax.tree_util.tree_leaves(sub)
        if f.ndim and len(sub_leaves) != 1:
            raise ValueError(
                f"`fixed` entry of shape {f.shape} stands for a subtree of theta0 with "
                f"{len(sub_leaves)} leaves; use one boolean for a whole subtree."
            )
        for t in sub_leaves:
            # One boolean for the whole leaf, or one per entry: a mask of another shape
            # would broadcast ((1,) fixing both entries of a (2,) leaf) silently.
            if f.ndim and f.shape != np.shape(t):
                raise ValueError(
                    f"`fixed` entry of shape {f.shape} does not fit a parameter of shape "
                    f"{np.shape(t)}: give one boolean for the whole parameter, or a mask of "
                    f"shape {np.shape(t)}."
                )
            parts.append(np.broadcast_to(f, np.shape(t)).reshape(-1))
    return np.concatenate(parts) if parts else np.zeros(0, bool)


def check_fixed_bounds(theta, fixed, lower, upper):
    """Warn about fixed entries of theta outside the box bounds of `constraints`: a fixed
    entry is not a variable, so `fit` keeps its given value and never projects it.

    **Arguments:**

    - `theta`: the parameters; `fixed`, `lower`, `upper`: flat over theta's entries (leaf
        order), the fixed mask and the bounds.
    """
    if not np.any(fixed):
        return
    values = _pytree.flat_host(theta)
    names = _pytree.leaf_names(theta)
    for i in np.flatnonzero(fixed):
        for side, bound, outside in (
            ("lower", lower[i], values[i] < lower[i]),
            ("upper", upper[i], values[i] > upper[i]),
        ):
            if outside:
                warn(
                    f"fixed parameter {names[i]!r} = {float(values[i])!r} is "
                    f"{'below' if side == 'lower' else 'above'} its {side} bound "
                    f"{float(bound)!r} of `constraints`: a fixed entry keeps its given value "
                    "(it is not projected); free it or move it inside the bounds.",
                    UserWarning,
                    stacklevel=4,
                )


def _none_as(value, fill):
    """A list or tuple of bounds (nested per record) with its None entries as `fill`."""
    if isinstance(value, (list, tuple)):
        return [fill if v is None else _none_as(v, fill) for v in value]
    return value


def check_x0_bounds(x0_bounds, shape, dtype, per_record=True, name="x0_bounds", estimated=None):
    """Bounds on x0 `(lower, upper)` checked (`fit(x0_bounds=...)`, `estimate_x0(bounds=
    ...)`): each None, a number, (n_x,) or, with `per_record`, (N, n_x); NaN refused,
    -inf / inf or a None entry of a list unbounded. Returns the lower and upper bounds
    broadcast to `shape` (N, n_x), the entries that `estimated` ((n_x,) booleans, or
    (N, n_x) with a mask per record; None for all) holds unbounded, or None where no
    entry is bounded."""
    if not isinstance(x0_bounds, (tuple, list)) or len(x0_bounds) != 2:
        raise TypeError(
            f"`{name}` must be a pair (lower, upper) of bounds on x0 (each None, a number, "
            f"an array (n_x,){' or (N, n_x)' if per_record else ''}), got "
            f"{type(x0_bounds).__name__}."
        )
    N, n_x = shape
    out = []
    for side, value, fill in (("lower", x0_bounds[0], -np.inf), ("upper", x0_bounds[1], np.inf)):
        if value is None:
            out.append(np.full(shape, fill, dtype))
            continue
        value = _none_as(value, fill)  # (an entry None: unbounded, as `constraints.box`)
        try:
            kind = np.asarray(value).dtype.kind
            a = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            kind = None
        if kind not in ("i", "u", "f"):
            raise TypeError(
                f"`{name}`'s {side} bound must be None, a number or an array of numbers, "
                + ("got booleans." if kind == "b" else f"got {type(value).__name__}.")
            )
        allowed = [(), (n_x,)] + ([(N, n_x)] if per_record else [])
        if a.shape not in allowed:
            rows = f" or ({N}, n_x) = ({N}, {n_x}), one per record" if per_record else ""
            raise ValueError(
                f"`{name}`'s {side} bound must have shape (n_x,) = ({n_x},){rows}, "
                f"got shape {a.shape}."
            )
        if np.isnan(a).any():
            raise ValueError(
                f"`{name}`'s {side} bound holds NaN: use -inf or inf for an unbounded entry."
            )
        if np.any(a == -fill):
            raise ValueError(
                f"`{name}`'s {side} bound holds {-fill}, which no value meets: use "
                f"{fill} for an unbounded entry."
            )
        out.append(np.broadcast_to(a, shape).astype(dtype))  # (a copy: written below)
    lower, upper = out
    if np.any(lower > upper):
        i = tuple(int(k) for k in np.argwhere(lower > upper)[0])
        raise ValueError(
            f"`{name}`: the lower bound is above the upper one at x0 entry {i[-1]}"
            + (f" of record {i[0]}" if N > 1 else "")
            + f" ({lower[i]} > {upper[i]})."
        )
    if not (np.isfinite(lower).any() or np.isfinite(upper).any()):
        return None
    if estimated is not None:  # (a held entry keeps its value: not bounded)
        held = np.broadcast_to(~np.asarray(estimated, bool), shape)
        lower[held], upper[held] = -np.inf, np.inf
    return lower, upper


def clip_x0(x0, box, name, what, stacklevel, warning=True):
    """x0 (..., n_x) clipped into `box` = (lower, upper) (broadcast against it), with a
    warning naming the entries that were outside where `warning` (the start of a fit or of an
    x0 estimate, which then starts from the clipped x0, as theta's projection of an
    infeasible start). `stacklevel`: that of the caller's frame."""
    clipped = np.clip(x0, *box).astype(np.asarray(x0).dtype)
    outside = clipped != x0
    if warning and outside.any():
        where = np.nonzero(outside)
        if outside.ndim >= 2 and outside.shape[-2] > 1:  # (several records: name each)
            pairs = sorted({(int(i), int(j)) for i, j in zip(where[-2], where[-1])})
            entries = "x0[" + "], x0[".join(f"{i}, {j}" for i, j in pairs[:10]) + "]"
            entries += f" and {len(pairs) - 10} more" if len(pairs) > 10 else ""
            said = f"in {entries} (record, state)"
        else:
            said = f"in its entries {sorted({int(j) for j in where[-1]})}"
        warn(
            f"the starting x0 lies outside `{name}` {said}: the {what} starts from x0 "
            "clipped into them.",
            stacklevel=stacklevel + 1,
        )
    return clipped


def x0_mask(estimate_x0, n_x) -> np.ndarray:
    """(n_x,) boolean mask of the initial-state entries to estimate."""
    if estimate_x0 is True or estimate_x0 is False:
        return np.full(n_x, estimate_x0)
    est = np.asarray(estimate_x0)
    if est.dtype == bool and est.ndim == 2 and est.shape[-1] == n_x:
        raise ValueError(
            f"`estimate_x0` must be a bool or a boolean mask of shape ({n_x},) here, one "
            f"mask for every record; got a mask of shape {est.shape}. A mask per record "
            "(N, n_x) is taken by `fit` on N records without `window` or `aggregate`."
        )
    if est.dtype != bool or est.shape not in ((), (n_x,)):
        raise ValueError(
            f"`estimate_x0` must be a bool or a boolean mask of shape ({n_x},), "
            f"got {estimate_x0!r}."
        )
    return np.broadcast_to(est, (n_x,)).copy()


def record_x0_mask(estimate_x0, shape, windowed, aggregated):
    """`fit(estimate_x0=...)` given a mask per record (N, n_x) (MATLAB's
    `InitialStates(i).Fixed` of a multi-experiment model, 1 x Ne), split into what the
    problem estimates: the entries estimated in any record (n_x,), and (N, n_x) those of
    them that a record holds at its value of `x0` (None where no record holds one the
    others estimate). Any other `estimate_x0` is returned as it is, with None."""
    est = np.asarray(estimate_x0) if isinstance(estimate_x0, (np.ndarray, list, tuple)) else None
    if est is None or est.ndim != 2:
        return estimate_x0, None
    N, n_x = shape
    expected = (
        f"`estimate_x0` must be a bool, a boolean mask of shape ({n_x},) for every record, "
        f"or one of shape (N, n_x) = ({N}, {n_x}), a mask per record; got "
    )
    if est.dtype != bool:
        raise ValueError(expected + f"an array of {est.dtype} (True / False entries are needed).")
    for refused, what in ((windowed, "`window`"), (aggregated, "`aggregate`")):
        if refused:
            raise ValueError(
                f"`estimate_x0` as a mask per record (shape {est.shape}) is not supported "
                f"with {what}: give one mask ({n_x},) for every "
                f"{'window' if windowed else 'record'}."
            )
    if est.shape != (N, n_x):
        raise ValueError(expected + f"a mask of shape {est.shape}.")
    union = est.any(axis=0)
    held = union[None, :] & ~est
    return union, (held if held.any() else None)
