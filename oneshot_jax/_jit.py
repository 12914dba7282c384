"""`jit`: compiled calls with `equinox.filter_jit`'s semantics and the library's options
for XLA's compiler, for the compiled calls that the public functions make at the top
level (`fit`'s solve, `predict`'s x0 solve, ...; never one that also runs inside another
compiled function: JAX takes compiler options on the outermost call only).

On a CPU, a first call spends most of its time in XLA generating machine code for each
fused kernel of the program. XLA's elemental emitter (`xla_cpu_use_fusion_emitters`
off) does so in about 40 % less time than its default MLIR fusion emitters, for the same
kernels (`benchmarks/first_call.py` shows the first calls); their numbers can differ in
the last bit from a call compiled without the option (the same function inside a user's
`jax.jit`: 1 ulp of a loss summed over records). The
options go to each compiled call (`jax.jit(compiler_options=...)`): the library never
changes JAX's global configuration. On another backend, or an XLA that no longer has the
option (jaxlib 0.11 dropped it), the call compiles with XLA's defaults: the first
compiled call on a CPU asks once per process (`compiler_options`).

A later call of a small problem is dominated by the dispatch around the program, so the
arguments are split once per call, without `equinox.filter_jit`'s per-call signature
binding, filtering and logging set-up: the arrays (JAX or NumPy) are the traced
arguments of one `jax.jit` per structure of the rest, which is static (hashed, as
`filter_jit` hashes it). Outputs come back the same way, their non-array leaves in the
treedef (`_Static`). Arguments whose static part cannot be hashed take
`equinox.filter_jit` itself.
"""

import functools

import equinox as eqx
import jax
import numpy as np

CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

# Whether this XLA takes `CPU_OPTIONS`: None until `compiler_options` first asks.
OPTIONS_TAKEN = [None]

_ARRAYS = (jax.Array, np.ndarray, np.generic)

# The compiled functions of each static structure, per `jit`; bounded.
_KEPT = 32


class _Static:
    """A value carried in a pytree's structure (no leaves): the non-array outputs."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value


jax.tree_util.register_pytree_node(_Static, lambda s: ((), s.value), lambda v, _: _Static(v))


def _split(tree):
    """(arrays, (treedef, the other leaves with None at the arrays))."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    arrays = [a for a in leaves if isinstance(a, _ARRAYS)]
    static = tuple(None if isinstance(a, _ARRAYS) else a for a in leaves)
    return arrays, (treedef, static)


def _merge(arrays, structure):
    treedef, static = structure
    it = iter(arrays)
    return jax.tree_util.tree_unflatten(treedef, [next(it) if s is None else s for s in static])


def compiler_options():
    """The compiler options of a compiled call on the default backend: `CPU_OPTIONS` on a
    CPU whose XLA takes them, else none.

    Whether XLA takes them is asked once per process, by compiling a one-element program
    with them (an XLA that does not know an option refuses the compilation): a later call
    never compiles twice, and never traces its function twice, to find out.

    **Returns:** a dict of options, possibly empty.
    """
    if jax.default_backend() != "cpu":
        return {}
    if OPTIONS_TAKEN[0] is None:
        probe = jax.jit(lambda x: x + 1, compiler_options=CPU_OPTIONS)
        try:
            probe.lower(np.zeros((), np.float32)).compile()
            OPTIONS_TAKEN[0] = True
        except Exception:  # any refusal of a one-element program means: not these options
            OPTIONS_TAKEN[0] = False
    return CPU_OPTIONS if OPTIONS_TAKEN[0] else {}


def _restate(err, cls, markers, said, rest):
    """Raise `cls(said + rest + JAX's message)` from `err` where its message holds every
    one of `markers` (JAX's refusal, met while tracing the model's functions) and was not
    restated already (by a compiled call inside: it starts with `said`); else return."""
    text = str(err)
    if not all(m in text for m in markers) or text.startswith(said):
        return
    raise cls(f"{said}{rest} (JAX: {err})") from err


def forward_mode_error(err: TypeError) -> None:
    """Re-raise JAX's refusal to differentiate a `jax.custom_vjp` in forward mode as a
    TypeError that says which of this library's derivatives need forward mode and what to
    do; return for any other TypeError."""
    _restate(
        err,
        TypeError,
        ("custom_vjp", "forward-mode"),
        "the model's `step`, `observe` or `rhs` calls a function with a `jax.custom_vjp`",
        ", which JAX cannot differentiate in forward mode, and this library differentiates "
        "the model in forward mode: the Jacobian of the least-squares solvers, the "
        "first-order tests and the standard errors of `fit`, `estimate_x0`, and the "
        "strategy 'jacobian' (which 'auto' takes for a small theta). Define that function's "
        "derivative with `jax.custom_jvp` instead; of the gradient paths only "
        "`value_and_grad(..., strategy='vjp')` works with a custom_vjp.",
    )


def callback_vmap_error(err: NotImplementedError) -> None:
    """Re-raise JAX's refusal to vmap a `jax.pure_callback` without a `vmap_method` as a
    NotImplementedError that says where this library vmaps the model and what to pass;
    return for any other error."""
    _restate(
        err,
        NotImplementedError,
        ("pure_callback", "vmap_method"),
        "the model's `step`, `observe` or `rhs` calls `jax.pure_callback` without a `vmap_method`",
        ", and this library maps the model over several evaluations at once (`jax.vmap`: "
        "the Jacobian's columns, the records, windows and starts of a fit): pass "
        '`vmap_method="sequential"` to `jax.pure_callback` ("expand_dims" where the '
        "function takes a leading axis of evaluations), and give the function a derivative "
        "with `jax.custom_jvp` (`fit` differentiates the model).",
    )


def reverse_mode_error(err: ValueError) -> None:
    """Re-raise JAX's refusal to differentiate a `lax.while_loop` in reverse mode as a
    ValueError that says which of this library's derivatives need reverse mode and what
    to do; return for any other error."""
    _restate(
        err,
        ValueError,
        ("Reverse-mode differentiation does not work for lax.while_loop",),
        "the model's `step`, `observe` or `rhs` has a `jax.lax.while_loop`",
        " (or a `fori_loop` whose bounds are not Python integers), which JAX cannot "
        "differentiate in reverse mode, and this library differentiates the model in "
        "reverse mode: the gradient (eq. 17, 20) of L-BFGS and Adam, the Jacobian's rows "
        "of a least-squares step with more than a few parameters. Iterate a fixed number "
        "of times (`lax.fori_loop` with integer bounds, `lax.scan`), or solve the implicit "
        "equation with `lax.custom_root` (differentiated implicitly).",
    )


def public_jit(fn):
    """`jit(fn)` for a public function's compiled call (`simulate`, `loss`,
    `value_and_grad`), which a user may also make inside a JAX transformation of their
    own (traced arguments, or a model that closes over traced values): there, where JAX
    refuses compiler options, it is `equinox.filter_jit(fn)`, inlined in the user's trace.

    **Arguments:** `fn`, the function to compile.

    **Returns:** the compiled function.
    """
    top = jit(fn)
    nested = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        leaves = jax.tree_util.tree_leaves((args, kwargs))
        if any(isinstance(a, jax.core.Tracer) for a in leaves):
            return nested(*args, **kwargs)
        try:
            return top(*args, **kwargs)
        except ValueError as err:
            if "inside a JAX transformation" not in str(err):
                raise
            return nested(*args, **kwargs)

    return call


def jit(fn):
    """`fn` compiled as `equinox.filter_jit(fn)` would (arrays traced, everything else
    static), with `CPU_OPTIONS` on a CPU whose XLA takes them (`compiler_options`).

    **Arguments:** `fn`, the function to compile.

    **Returns:** the compiled function.
    """
    plain = eqx.filter_jit(fn)
    tuned = eqx.filter_jit(fn, compiler_options=CPU_OPTIONS)
    compiled = {}  # (structure, options?) -> jax.jit of the arrays

    def traced(structure, arrays):
        args, kwargs = _merge(arrays, structure)
        out_arrays, out_structure = _split(fn(*args, **kwargs))
        return out_arrays, _Static(out_structure)

    traced.__name__, traced.__qualname__ = fn.__name__, fn.__qualname__  # (XLA's names)

    def fast(structure, arrays, options):
        key = (structure, options)
        f = compiled.get(key)
        if f is None:
            if len(compiled) >= _KEPT:
                compiled.pop(next(iter(compiled)))
            kw = {"compiler_options": CPU_OPTIONS} if options else {}
            f = compiled[key] = jax.jit(functools.partial(traced, structure), **kw)
        try:
            out_arrays, out_structure = f(arrays)
        except TypeError as err:
            forward_mode_error(err)
            raise
        except NotImplementedError as err:
            callback_vmap_error(err)
            raise
        except ValueError as err:
            reverse_mode_error(err)
            if "top-level" not in str(err):
                raise
            # (JAX refuses compiler options on a nested jit: this call is inside a trace)
            raise ValueError(
                f"oneshot_jax's host-side solve ({fn.__name__}) was called inside a JAX "
                "transformation (jax.jit, vmap, grad), through its arguments or through what "
                "the model closes over: `fit`, `estimate_x0` and `predict` run on the host; "
                "call them outside the transformation."
            ) from None
        return _merge(out_arrays, out_structure.value)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        options = bool(compiler_options())
        arrays, structure = _split((args, kwargs))
        try:
            hash(structure)
        except TypeError:  # an unhashable static leaf: equinox's own handling
            return (tuned if options else plain)(*args, **kwargs)
        return fast(structure, arrays, options)

    return call
