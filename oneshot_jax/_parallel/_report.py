"""Reporting the sequential fallback of a parallel rollout to the host.

A parallel rollout that does not converge falls back to the sequential loop: the states
are the same, only slower. With `ParallelInTime(fallback=False)` it keeps Newton's best
iterate instead, whose states, loss and gradient are not the model's. The compiled code
reports each rollout (whether it fell back, whether it converged) by a host callback.
`fit` counts them over its run (`counting`), reports the counts in `FitResult.diagnostics`
and warns; `simulate`, `loss` and `value_and_grad` count them over their call and warn at
their caller's line (`warn_counted`) after it. A rollout that runs outside such a call
(under the user's own `jax.jit`) warns from the callback itself, every time.
"""

import threading

import jax
import numpy as np

from .._caller_warnings import warn, warn_each_time

# The open counting calls, per thread of their caller (each thread's innermost last): a
# callback counts for its own thread's innermost call, or, run on a thread of XLA's own
# (a GPU's), for the one thread with an open call; with several, it cannot tell whose
# rollout it reports, and warns from the callback instead.
_STACKS: dict = {}
_LOCK = threading.Lock()


class counting:
    """Context manager: count the parallel rollouts and their fallbacks instead of
    warning (`fit` wraps its compiled call in it). With `active=False` (a call whose
    strategy is sequential) the counts stay zero and the call is not waited for."""

    def __init__(self, active=True):
        self.active = active

    def __enter__(self):
        self.counts = {"parallel_rollouts": 0, "sequential_fallbacks": 0, "unconverged_rollouts": 0}
        if self.active:
            with _LOCK:
                _STACKS.setdefault(threading.get_ident(), []).append(self.counts)
        return self.counts

    def __exit__(self, *exc):
        if self.active:
            jax.effects_barrier()
            with _LOCK:
                thread = threading.get_ident()
                stack = _STACKS[thread]
                # (by identity: another call's counts may equal these)
                del stack[next(i for i, c in enumerate(stack) if c is self.counts)]
                if not stack:
                    del _STACKS[thread]
        return False


UNCONVERGED = (
    "the parallel rollout did not converge and `ParallelInTime(fallback=False)` kept "
    "Newton's best iterate: its states, and the loss and gradient computed from them, are "
    "not those of the model. Use the default fallback=True (the sequential loop), or the "
    "sequential strategy, for these dynamics."
)


FELL_BACK = (
    "the parallel rollout did not converge (unstable or chaotic dynamics, or a record too "
    "long for Newton's method) and fell back to the sequential loop where it did not (the "
    "record, or with `chunk_size` those chunks): every state is the model's step of the "
    "one before to round-off (with chunks of chaotic dynamics, not necessarily the "
    "sequential rollout's trajectory: see the parallel guide)."
)


def _messages(counts):
    """The warnings a call's counted rollouts ask for (`counting`'s counts)."""
    out = []
    if counts["unconverged_rollouts"]:
        out.append(UNCONVERGED)
    if counts["sequential_fallbacks"]:
        out.append(FELL_BACK)
    return out


def warn_counted(counts, stacklevel=1):
    """Warn of the rollouts a call counted (`counting`) that kept Newton's unconverged
    iterate or fell back to the sequential loop, at the line `stacklevel` frames above the
    caller (as `warnings.warn`), after the call: the user's filters decide each at that
    line, and an "error" filter raises it there."""
    for message in _messages(counts):
        warn(message, RuntimeWarning, stacklevel=stacklevel + 1)


def _host(fallback, converged):
    fallback = np.asarray(fallback).reshape(-1)
    kept = ~np.asarray(converged).reshape(-1) & ~fallback  # the best iterate, not the model's
    counts = {
        "parallel_rollouts": int(fallback.size),
        "sequential_fallbacks": int(np.sum(fallback)),
        "unconverged_rollouts": int(np.sum(kept)),
    }
    with _LOCK:
        stack = _STACKS.get(threading.get_ident())
        if stack is None and len(_STACKS) == 1:  # (a callback on a thread of XLA's)
            (stack,) = _STACKS.values()
        if stack:
            for key, n in counts.items():
                stack[-1][key] += n
            return
    # A rollout outside a counting call (under the user's `jax.jit`), or one whose call
    # cannot be told among the calls of several threads: warned from here, every such
    # rollout (not the first alone: all come from this one line).
    for message in _messages(counts):
        warn_each_time(message, RuntimeWarning, __file__)


def report(info):
    """Send a `RolloutInfo`'s fallback and convergence flags to the host (inside compiled
    code)."""
    jax.debug.callback(_host, info.fallback, info.converged)
