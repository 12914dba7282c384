"""`jit`: `equinox.filter_jit` with the library's options for XLA's compiler, for the
compiled calls that the public functions make at the top level (`fit`'s solve,
`predict`'s x0 solve, ...; never one that also runs inside another compiled function:
JAX takes compiler options on the outermost call only).

On a CPU, a first call spends most of its time in XLA generating machine code for each
fused kernel of the program. XLA's elemental emitter (`xla_cpu_use_fusion_emitters`
off) does so in about 40 % less time than its default MLIR fusion emitters, for the same
kernels and the same numbers (`benchmarks/first_call.py` shows the first calls). The
options go to each compiled call (`jax.jit(compiler_options=...)`): the library never
changes JAX's global configuration. On another backend, or an XLA that no longer has the
option, the call compiles with XLA's defaults.
"""

import functools

import equinox as eqx
import jax

CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

# Whether this XLA takes `CPU_OPTIONS` (set False on its first refusal).
OPTIONS_TAKEN = [True]


def jit(fn):
    """`equinox.filter_jit(fn)`, compiled with `CPU_OPTIONS` on the CPU backend.

    **Arguments:** `fn`, the function to compile (arrays traced, everything else static,
    as `equinox.filter_jit`).

    **Returns:** the compiled function.
    """
    plain = eqx.filter_jit(fn)
    tuned = eqx.filter_jit(fn, compiler_options=CPU_OPTIONS)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if OPTIONS_TAKEN[0] and jax.default_backend() == "cpu":
            try:
                return tuned(*args, **kwargs)
            except jax.errors.JaxRuntimeError as e:
                if "compile option" not in str(e):
                    raise
                OPTIONS_TAKEN[0] = False
        return plain(*args, **kwargs)

    return call
