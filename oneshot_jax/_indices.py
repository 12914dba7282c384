"""Constant indices past the end of an array in the user's model, found on its jaxpr.

JAX clamps an index that is out of range instead of raising: `u[1]` of a record with one
input column reads `u[0]`, `x[2]` of a two-state x0 reads `x[1]`, and the fit then runs on
a wrong model without a word. The indices written in a model are constants of its jaxpr
(`u[1]` is a `dynamic_slice` at the constant 1, `u[jnp.array([0, 1])]` a `gather` at a
constant array), so they are checked here on the trace that the structural checks make
anyway: the integer arithmetic on constants is evaluated in NumPy (no XLA program is
compiled), and every `dynamic_slice` and clamping `gather` whose start indices are known
is checked against its operand's shape. Indices computed from the data are unknown and
left alone; a gather that fills (`jnp.take`'s default mode) gives NaN, not a silent read.
"""

import jax
import numpy as np
from jax.extend.core import Literal

_ELEMENTWISE = {
    "add": np.add,
    "sub": np.subtract,
    "mul": np.multiply,
    "neg": np.negative,
    "max": np.maximum,
    "min": np.minimum,
    "lt": np.less,
    "le": np.less_equal,
    "gt": np.greater,
    "ge": np.greater_equal,
    "eq": np.equal,
    "ne": np.not_equal,
    "and": np.logical_and,
    "or": np.logical_or,
    "not": np.logical_not,
    "rem": np.fmod,
}


def _evaluate(eqn, values):
    """The output of an integer-arithmetic or shape equation on known inputs, else None."""
    name, p = eqn.primitive.name, eqn.params
    if name in _ELEMENTWISE:
        return _ELEMENTWISE[name](*values)
    if name == "select_n":
        which, *cases = values
        return np.choose(np.asarray(which, int), np.broadcast_arrays(*cases))
    if name == "clamp":
        lo, x, hi = values
        return np.clip(x, lo, hi)
    if name == "convert_element_type":
        return np.asarray(values[0]).astype(np.dtype(p["new_dtype"]))
    if name == "broadcast_in_dim":
        x = np.asarray(values[0])
        shape = [1] * len(p["shape"])
        for k, d in enumerate(p["broadcast_dimensions"]):
            shape[d] = x.shape[k]
        return np.broadcast_to(x.reshape(shape), p["shape"])
    if name == "reshape":
        return np.reshape(values[0], p["new_sizes"])
    if name == "squeeze":
        return np.squeeze(values[0], axis=tuple(p["dimensions"]))
    if name == "concatenate":
        return np.concatenate(values, axis=p["dimension"])
    return None


def _sub_jaxprs(eqn):
    """The jaxprs an equation calls, with whether its operands feed their inputs one to
    one (a call: jit, custom_jvp/vjp, remat) or not (loops, branches: inputs unknown)."""
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr", "body_jaxpr", "cond_jaxpr"):
        sub = eqn.params.get(key)
        if sub is not None and (hasattr(sub, "eqns") or hasattr(sub, "jaxpr")):
            call = eqn.primitive.name not in ("scan", "while")
            yield sub, call
    for sub in eqn.params.get("branches", ()):
        yield sub, False


def _check(jaxpr, known_in, found):
    """Append to `found` the known start indices past the end of their operand, in
    `jaxpr` (closed or not) and the jaxprs it calls; `known_in`: its inputs' known values
    (None: unknown)."""
    inner = jaxpr.jaxpr if hasattr(jaxpr, "jaxpr") else jaxpr
    consts = list(getattr(jaxpr, "consts", ()))
    known = {}

    def value(v):
        if isinstance(v, Literal):
            return np.asarray(v.val)
        return known.get(v)

    for v, c in zip(inner.constvars, consts):
        if not isinstance(c, jax.core.Tracer) and hasattr(c, "__array__"):
            known[v] = np.asarray(c)
    for v, k in zip(inner.invars, known_in):
        if k is not None:
            known[v] = k
    for eqn in inner.eqns:
        name = eqn.primitive.name
        values = [value(v) for v in eqn.invars]
        if name == "dynamic_slice":
            operand, starts = eqn.invars[0], values[1:]
            shape, sizes = operand.aval.shape, eqn.params["slice_sizes"]
            for d, s in enumerate(starts):
                if s is not None and not 0 <= int(s) <= shape[d] - sizes[d]:
                    found.append((shape, d, int(s)))
        elif name == "gather" and values[1] is not None:
            mode = str(eqn.params["mode"])
            if "FILL" not in mode:
                operand = eqn.invars[0]
                dims = eqn.params["dimension_numbers"].start_index_map
                sizes = eqn.params["slice_sizes"]
                idx = np.asarray(values[1]).reshape(-1, len(dims))
                for k, d in enumerate(dims):
                    bad = (idx[:, k] < 0) | (idx[:, k] > operand.aval.shape[d] - sizes[d])
                    if bad.any():
                        found.append((operand.aval.shape, d, int(idx[bad, k][0])))
        for sub, call in _sub_jaxprs(eqn):
            _check(sub, values if call else [None] * len(values), found)
        if all(v is not None for v in values) and len(eqn.outvars) == 1:
            try:
                out = _evaluate(eqn, values)
            except (ValueError, TypeError):
                out = None
            if out is not None:
                known[eqn.outvars[0]] = np.asarray(out)


def out_of_range(fn, *args) -> list:
    """The constant indices of `fn(*args)` (abstract arguments) past the end of their
    array, as (the array's shape, the axis, the index); empty where there are none or
    where `fn` cannot be traced to a jaxpr."""
    try:
        closed = jax.make_jaxpr(fn)(*args)
    except Exception:  # (the abstract checks report a model that does not trace)
        return []
    found = []
    _check(closed, [None] * len(closed.jaxpr.invars), found)
    return found
