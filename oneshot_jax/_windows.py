"""Cutting one long record into windows, each with an initial state of its own."""

import warnings

import numpy as np

from ._x0_lsq import solve_x0


def window_starts(data, u_w, z_w, mask_w=None):
    """Each window's starting state from its own samples with theta0, for `fit(window=)`
    on a partly observed state: x0-only Gauss-Newton on all windows at once (one
    `_x0_lsq.solve_x0` of N trajectories), from the record's x0 as the guess; the first
    window keeps the given x0."""
    N = u_w.shape[0]
    guess = np.broadcast_to(np.asarray(data.x0), (N, np.shape(data.x0)[-1]))
    windows = data._replace(x0=guess, u=u_w, z=z_w, mask=mask_w, batched=True, lengths=None)
    r = solve_x0(windows, with_covariance=False)
    observed = np.ones(r.residuals.shape, bool) if mask_w is None else mask_w.outputs > 0
    finite = np.all(np.isfinite(r.residuals) | ~observed, axis=(1, 2)) & np.all(
        np.isfinite(r.x0), axis=1
    )
    if not np.all(finite):
        bad = [int(i) for i in np.flatnonzero(~finite)]
        raise ValueError(
            f"theta0 makes the model blow up (NaN or inf) within windows {bad} of "
            f"{u_w.shape[1]} samples: each window's starting state is estimated from its "
            "own samples by simulating it with theta0. Start from parameters that keep the "
            "model stable over a window, use shorter windows, or give each window's "
            f"starting state as `x0` of shape ({N}, {guess.shape[1]})."
        )
    x0_w = np.array(r.x0, dtype=np.asarray(data.x0).dtype)
    x0_w[0] = np.asarray(data.x0)
    return x0_w


def cut(data, window, x0_windows=None):
    """Consecutive windows of `window` samples from one record, as N trajectories:
    (x0_w (N, n_x), u_w (N, window, n_u), z_w (N, window, n_z), mask_w (or None)).

    Each window's starting state is `x0_windows[i]` when given; else it is taken from z
    where the model observes its whole state (z = x), else estimated from the window's
    own samples with the starting parameters (`window_starts`); the first window starts
    at the given x0.
    """
    u, z, x0 = data.u, data.z, data.x0
    T = u.shape[0]
    if isinstance(window, bool) or int(window) != window or window < 1:
        raise ValueError(f"`window` must be a positive integer, got {window!r}.")
    window = int(window)
    if window > T:
        raise ValueError(f"`window` ({window}) is longer than the record (T = {T}).")
    N = T // window
    if N * window != T:
        warnings.warn(
            f"the last {T - N * window} samples do not fill a window and are dropped.", stacklevel=4
        )
    u_w = np.asarray(u[: N * window]).reshape(N, window, -1)
    z_w = np.asarray(z[: N * window]).reshape(N, window, -1)
    mask_w = None
    if data.mask is not None:
        mask_w = type(data.mask)(
            np.asarray(data.mask.outputs[: N * window]).reshape(N, window, -1),
            np.asarray(data.mask.samples[: N * window]).reshape(N, window),
        )
    if x0_windows is not None:
        x0_w = np.asarray(x0_windows)
        if x0_w.shape != (N, np.shape(x0)[-1]):
            raise ValueError(
                f"`x0` of shape {x0_w.shape} gives one starting state per window, but the "
                f"record of T = {T} samples holds {N} windows of {window}: expected shape "
                f"({N}, {np.shape(x0)[-1]})."
            )
    elif data.model.observes_state:
        x0_w = np.array(z_w[:, 0, :], dtype=np.asarray(x0).dtype)
        x0_w[0] = np.asarray(x0)
    else:
        x0_w = window_starts(data, u_w, z_w, mask_w)
    return x0_w, u_w, z_w, mask_w
