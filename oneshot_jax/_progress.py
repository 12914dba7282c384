"""Progress of a long fit, shown from inside the compiled loop (the pattern of diffrax's
`TqdmProgressMeter`): the loop calls back to the host every `refresh_steps` steps with
the step count and the best loss over the starts; the bar lives on the host."""

import itertools
import threading

import equinox as eqx
import jax
import numpy as np

from ._counts import integral

_BARS: dict[int, object] = {}
_LOCK = threading.Lock()
_IDS = itertools.count(1)


class TqdmProgress(eqx.Module):
    """A tqdm progress bar with the loss, refreshed every `refresh_steps` steps.

    A progress object of one's own (`fit(progress=...)`) has its methods: `open` and
    `close` run on the host, `update` (every step) and, where it has one, `finish` (once
    after each solver's loop) inside the compiled loop, where they show values through
    `jax.debug.callback`.

    **Arguments:**

    - `refresh_steps`: steps between two updates of the bar (each update is one host
        callback from the compiled loop).
    """

    refresh_steps: int = eqx.field(default=10, converter=integral)

    def __check_init__(self):
        r = self.refresh_steps
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 1:
            raise ValueError(
                f"`TqdmProgress(refresh_steps=...)` must be an integer >= 1, got {r!r}."
            )

    def open(self, total: int, description: str = "fit") -> int:
        """Create the bar on the host; returns its id, passed into the compiled loop."""
        import tqdm

        bar = tqdm.tqdm(total=total, desc=description, unit="step", dynamic_ncols=True)
        with _LOCK:
            bar_id = next(_IDS)
            _BARS[bar_id] = bar
        return bar_id

    def close(self, bar_id: int):
        """Close the bar `bar_id` on the host (after the fit, also when it failed)."""
        with _LOCK:
            bar = _BARS.pop(bar_id, None)
        if bar is not None:
            bar.close()

    def update(self, bar_id, offset, step, loss):
        """Called inside the loop with the step shared by the starts: every
        `refresh_steps` steps, move the bar to `offset + step` and show `loss` (the
        smallest over the starts: those running, and with the starts in turn the final
        losses of those done)."""
        jax.lax.cond(
            step % self.refresh_steps == 0,
            lambda: jax.debug.callback(_show, bar_id, offset + step, loss),
            lambda: None,
        )

    def finish(self, bar_id, offset, step, loss):
        """Called once after each solver's loop: move the bar to the step the solver
        stopped at and show the loss there, whatever `refresh_steps` (a refresh alone
        would leave the bar at the last multiple of it)."""
        jax.debug.callback(_show, bar_id, offset + step, loss)


def _show(bar_id, n, loss):
    """On the host: move the bar `bar_id` to step `n` and show `loss`."""
    with _LOCK:
        bar = _BARS.get(int(bar_id))
    if bar is not None:
        bar.n = int(n)
        bar.set_postfix_str(f"loss {float(loss):.6e}")


class NoProgress(eqx.Module):
    """No progress bar (the default of `fit`)."""

    def open(self, total: int, description: str = "fit") -> int:
        """No bar to create: returns the id 0."""
        return 0

    def close(self, bar_id: int):
        """No bar to close."""

    def update(self, bar_id, offset, step, loss):
        """Nothing to show."""

    def finish(self, bar_id, offset, step, loss):
        """Nothing to show."""
