"""Reporting the sequential fallback of a parallel rollout to the host.

A parallel rollout that does not converge falls back to the sequential loop: the states
are the same, only slower. With `ParallelInTime(fallback=False)` it keeps Newton's best
iterate instead, whose states, loss and gradient are not the model's. The compiled code
reports each rollout (whether it fell back, whether it converged) by a host callback.
Outside `fit` each is a warning; `fit` counts them over its run, reports the counts in
`FitResult.diagnostics` and warns.
"""

import threading

import jax
import numpy as np

from .._caller_warnings import warn

# Process-wide (host callbacks run on XLA's threads, not the caller's).
_STACK: list = []
_LOCK = threading.Lock()


class counting:
    """Context manager: count the parallel rollouts and their fallbacks instead of
    warning (`fit` wraps its compiled call in it)."""

    def __enter__(self):
        self.counts = {"parallel_rollouts": 0, "sequential_fallbacks": 0, "unconverged_rollouts": 0}
        with _LOCK:
            _STACK.append(self.counts)
        return self.counts

    def __exit__(self, *exc):
        jax.effects_barrier()
        with _LOCK:
            _STACK.remove(self.counts)
        return False


UNCONVERGED = (
    "the parallel rollout did not converge and `ParallelInTime(fallback=False)` kept "
    "Newton's best iterate: its states, and the loss and gradient computed from them, are "
    "not those of the model. Use the default fallback=True (the sequential loop), or the "
    "sequential strategy, for these dynamics."
)


def _host(fallback, converged):
    fallback = np.asarray(fallback).reshape(-1)
    kept = ~np.asarray(converged).reshape(-1) & ~fallback  # the best iterate, not the model's
    with _LOCK:
        if _STACK:
            _STACK[-1]["parallel_rollouts"] += int(fallback.size)
            _STACK[-1]["sequential_fallbacks"] += int(np.sum(fallback))
            _STACK[-1]["unconverged_rollouts"] += int(np.sum(kept))
            return
    if np.any(kept):
        warn(UNCONVERGED, RuntimeWarning, stacklevel=2)
    if np.any(fallback):
        warn(
            "the parallel rollout did not converge (unstable or chaotic dynamics, or a "
            "record too long for Newton's method) and fell back to the sequential loop "
            "where it did not (the record, or with `chunk_size` those chunks): every state "
            "is the model's step of the one before to round-off (with chunks of chaotic "
            "dynamics, not necessarily the sequential rollout's trajectory: see the "
            "parallel guide).",
            RuntimeWarning,
            stacklevel=2,
        )


def report(info):
    """Send a `RolloutInfo`'s fallback and convergence flags to the host (inside compiled
    code)."""
    jax.debug.callback(_host, info.fallback, info.converged)
