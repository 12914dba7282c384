"""Cutting one long record into windows, each with an initial state of its own."""

import equinox as eqx
import numpy as np

from ._caller_warnings import warn
from ._counts import integral, is_count
from ._x0_lsq import solve_x0


class BlowUp(ValueError):
    """theta makes the model blow up within windows (`window_starts`): a multistart fit
    tries its next start (`_fit_inputs.check_inputs`)."""


def window_starts(data, u_w, z_w, mask_w=None, keep_first=True):
    """Each window's starting state from its own samples with theta0, for `fit(window=)`
    on a partly observed state: x0-only Gauss-Newton on all windows at once (one
    `_x0_lsq.solve_x0` of N trajectories), from the record's x0 as the guess; the first
    window keeps the given x0 (with `keep_first`: it starts at sample 0)."""
    N = u_w.shape[0]
    guess = np.broadcast_to(np.asarray(data.x0), (N, np.shape(data.x0)[-1]))
    if guess.shape[1] == 0:  # a model without state (n_x = 0): nothing to estimate
        return np.zeros(guess.shape, np.asarray(data.x0).dtype)
    windows = data._replace(x0=guess, u=u_w, z=z_w, mask=mask_w, batched=True, lengths=None)
    r = solve_x0(windows, with_covariance=False)
    observed = np.ones(r.residuals.shape, bool) if mask_w is None else mask_w.outputs > 0
    finite = np.all(np.isfinite(r.residuals) | ~observed, axis=(1, 2)) & np.all(
        np.isfinite(r.x0), axis=1
    )
    if not np.all(finite):
        bad = [int(i) for i in np.flatnonzero(~finite)]
        raise BlowUp(
            f"theta0 makes the model blow up (NaN or inf) within windows {bad} of "
            f"{u_w.shape[1]} samples: each window's starting state is estimated from its "
            "own samples by simulating it with theta0. Start from parameters that keep the "
            "model stable over a window, use shorter windows, or give each window's "
            f"starting state as `x0` of shape ({N}, {guess.shape[1]})."
        )
    x0_w = np.array(r.x0, dtype=np.asarray(data.x0).dtype)
    if keep_first:
        x0_w[0] = np.asarray(data.x0)
    return x0_w


class Windows(eqx.Module):
    """Windows of one long record for `fit(window=...)` (multiple shooting: each window is
    simulated from an initial state of its own, estimated with theta), when not all of
    the consecutive windows of `fit(window=length)` are wanted.

    **Arguments:**

    - `length`: the samples per window (alone: the consecutive windows of
        `fit(window=length)`, whose samples past the last whole window `fit` warns of).
    - `every`: take every k-th of the consecutive windows (0, length, 2 length, ...).
    - `count`: take this many of them, spread evenly over the consecutive windows (the
        first and the last of those included: samples past the last whole window, fewer
        than `length`, are in none). Not with `every`.
    - `starts`: the windows' first samples, given (sorted, each window within the
        record; windows may overlap, but the standard errors then count a sample once per
        window it lies in and are not those of the record: `fit` warns). Not with
        `every` or `count`.

    The windows that start at sample 0 starts from `fit`'s `x0`; every other window's
    starting state is read off z where the model observes its whole state, and
    otherwise estimated from its own samples with theta0. `FitResult.window_starts`
    says where each row of `FitResult.x0` starts.
    """

    length: int = eqx.field(static=True)
    every: int = eqx.field(static=True, default=1)
    count: int | None = eqx.field(static=True, default=None)
    starts: tuple | None = eqx.field(static=True, default=None)

    def __init__(self, length, *, every=1, count=None, starts=None):
        for name, v, low in (("length", length, 1), ("every", every, 1)):
            if not is_count(v, low):
                raise ValueError(f"`Windows({name}=...)` must be an integer >= {low}, got {v!r}.")
        if count is not None and not is_count(count, 1):
            raise ValueError(
                f"`Windows(count=...)` must be None or an integer >= 1, got {count!r}."
            )
        length, every = int(length), int(every)
        count = None if count is None else int(count)
        if count is not None and every != 1:
            raise ValueError(
                "`Windows(count=...)` does not combine with `every`: `count` spreads its "
                "windows over the record, `every` takes every k-th; pick one."
            )
        if starts is not None:
            if every != 1 or count is not None:
                raise ValueError("`Windows(starts=...)` does not combine with `every` or `count`.")
            given = starts
            if np.ndim(starts) == 1:  # (whole numbers as floats, as `fit(window=50.0)`)
                starts = [integral(s) for s in np.asarray(starts).tolist()]
            arr = np.asarray(starts)
            if arr.ndim != 1 or arr.size == 0 or not np.issubdtype(arr.dtype, np.integer):
                raise ValueError(
                    f"`Windows(starts=...)` must be a non-empty 1-D sequence of sample indices, "
                    f"got {given!r}."
                )
            if np.any(np.diff(arr) <= 0) or arr[0] < 0:
                raise ValueError("`Windows(starts=...)` must be non-negative and increasing.")
            starts = tuple(int(s) for s in arr)
        self.length, self.every, self.count, self.starts = int(length), int(every), count, starts

    def first_samples(self, T) -> np.ndarray:
        """The windows' first samples in a record of T samples."""
        if self.length > T:
            raise ValueError(f"`window` ({self.length}) is longer than the record (T = {T}).")
        if self.starts is not None:
            s = np.asarray(self.starts)
            if s[-1] + self.length > T:
                raise ValueError(
                    f"`Windows(starts=...)`: the window at {int(s[-1])} of {self.length} samples "
                    f"ends after the record (T = {T})."
                )
            return s
        s = np.arange(T // self.length) * self.length
        if self.count is not None:
            if self.count > s.size:
                raise ValueError(
                    f"`Windows(count={self.count})`: the record (T = {T}) holds only {s.size} "
                    f"windows of {self.length} samples."
                )
            s = s[np.unique(np.round(np.linspace(0, s.size - 1, self.count)).astype(int))]
        if self.every > 1 and s.size > 1 and self.every >= s.size:
            # (a stride read as samples, not windows, would fit one window without a word)
            raise ValueError(
                f"`Windows(every={self.every})` takes one window in {self.every}, but the "
                f"record (T = {T}) holds only {s.size} windows of {self.length} samples: it "
                f"would keep the first alone. `every` counts windows, not samples; for one "
                f"window take `Windows({self.length}, count=1)`."
            )
        return s[:: self.every]


def as_windows(window):
    """`fit`'s `window=`: a `Windows`, from an integer (consecutive windows) or itself."""
    if isinstance(window, Windows):
        return window
    if not is_count(window, 1):
        schedule = (
            " (a schedule of window lengths is `oneshot_jax.fit_continuation(windows=...)`)"
            if isinstance(window, (list, tuple))
            else ""
        )
        raise ValueError(
            f"`window` must be a positive integer or an `oneshot_jax.Windows`, got "
            f"{window!r}{schedule}."
        )
    return Windows(int(window))


def cut(data, window, x0_windows=None):
    """Windows of one record as N trajectories: (x0_w (N, n_x), u_w (N, length, n_u),
    z_w (N, length, n_z), mask_w (or None), starts (N,), unread).

    `window`: an integer (consecutive windows of that many samples) or a `Windows`. Each
    window's starting state is `x0_windows[i]` when given; else it is taken from z where
    the model observes its whole state (z = x), else estimated from the window's own
    samples with the starting parameters (`window_starts`); a window at sample 0 starts
    at the given x0. A sixth value, `unread` (N, n_x) or None: the entries taken from a
    first sample of z that is missing (0 there; `build_problem` refuses to hold them).
    """
    u, z, x0 = data.u, data.z, data.x0
    T = u.shape[0]
    consecutive = not isinstance(window, Windows)
    window = as_windows(window)
    starts = window.first_samples(T)
    length = window.length
    N = starts.size
    covered = int(starts[-1]) + length
    # (`Windows(length)` alone is the same windows as the integer: the same warning)
    every_window = window.every == 1 and window.count is None and window.starts is None
    if every_window and covered != T:
        warn(f"the last {T - covered} samples do not fill a window and are dropped.", stacklevel=4)
    rows = starts[:, None] + np.arange(length)[None, :]  # (N, length) sample indices
    copies = np.bincount(rows.ravel(), minlength=T)
    if copies.max() > 1:
        mean = float(copies.sum() / np.count_nonzero(copies))
        warn(
            f"the windows overlap: a sample lies in up to {int(copies.max())} windows "
            f"({mean:.3g} on average). The covariance counts each copy as an independent "
            "observation, each window with an initial state of its own, so the standard "
            "errors are not those of the record: they can be too small or too large, by "
            "an amount that differs between parameters; windows that do not overlap give "
            "honest ones.",
            stacklevel=4,
        )

    def take(a):
        a = np.asarray(a)
        return a[: N * length].reshape(N, length, *a.shape[1:]) if consecutive else a[rows]

    u_w, z_w = take(u), take(z)
    mask_w = unread = None
    if data.mask is not None:
        mask_w = type(data.mask)(take(data.mask.outputs), take(data.mask.samples))
    if x0_windows is not None:
        x0_w = np.asarray(x0_windows)
        if x0_w.shape != (N, np.shape(x0)[-1]):
            raise ValueError(
                f"`x0` of shape {x0_w.shape} gives one starting state per window, but the "
                f"record of T = {T} samples holds {N} windows of {length}: expected shape "
                f"({N}, {np.shape(x0)[-1]})."
            )
    elif data.model.observes_state:
        x0_w = np.array(z_w[:, 0, :], dtype=np.asarray(x0).dtype)
        if mask_w is not None:  # (a missing first sample reads 0 there)
            out = np.asarray(mask_w.outputs)
            first = out[:, 0] if out.ndim == 3 else np.broadcast_to(out[:, :1], x0_w.shape)
            unread = np.array(first == 0)
        if starts[0] == 0:
            x0_w[0] = np.asarray(x0)
            if unread is not None:
                unread[0] = False
    else:
        x0_w = window_starts(data, u_w, z_w, mask_w, keep_first=bool(starts[0] == 0))
    return x0_w, u_w, z_w, mask_w, starts, unread
