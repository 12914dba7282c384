"""Reporting the sequential fallback of a parallel rollout to the host.

A parallel rollout that does not converge falls back to the sequential loop: the states
are the same, only slower. The compiled code reports each rollout (and whether it fell
back) by a host callback. Outside `fit` a fallback is a warning; `fit` counts them over
its run and reports the counts in `FitResult.diagnostics`.
"""

import threading
import warnings

import jax
import numpy as np

# Process-wide (host callbacks run on XLA's threads, not the caller's).
_STACK: list = []
_LOCK = threading.Lock()


class counting:
    """Context manager: count the parallel rollouts and their fallbacks instead of
    warning (`fit` wraps its compiled call in it)."""

    def __enter__(self):
        self.counts = {"parallel_rollouts": 0, "sequential_fallbacks": 0}
        with _LOCK:
            _STACK.append(self.counts)
        return self.counts

    def __exit__(self, *exc):
        jax.effects_barrier()
        with _LOCK:
            _STACK.remove(self.counts)
        return False


def _host(fallback):
    fallback = np.asarray(fallback).reshape(-1)
    with _LOCK:
        if _STACK:
            _STACK[-1]["parallel_rollouts"] += int(fallback.size)
            _STACK[-1]["sequential_fallbacks"] += int(np.sum(fallback))
            return
    if np.any(fallback):
        warnings.warn(
            "the parallel rollout did not converge (unstable or chaotic dynamics, or a "
            "record too long for Newton's method) and fell back to the sequential loop: "
            "the result is exact, but computed sequentially.",
            RuntimeWarning,
            stacklevel=2,
        )


def report(info):
    """Send a `RolloutInfo`'s fallback flag to the host (inside compiled code)."""
    jax.debug.callback(_host, info.fallback)
