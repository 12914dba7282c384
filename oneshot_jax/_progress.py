"""Progress of a long fit, shown from inside the compiled loop (the pattern of diffrax's
`TqdmProgressMeter`): the loop calls back to the host every `refresh_steps` steps with
the step count and the best loss over the starts; the bar lives on the host."""

import itertools
import threading

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

_BARS: dict[int, object] = {}
_LOCK = threading.Lock()
_IDS = itertools.count(1)


class TqdmProgress(eqx.Module):
    """A tqdm progress bar with the loss, refreshed every `refresh_steps` steps.

    **Arguments:**

    - `refresh_steps`: steps between two updates of the bar (each update is one host
        callback from the compiled loop).
    """

    refresh_steps: int = 10

    def open(self, total: int, description: str = "fit") -> int:
        """Create the bar on the host; returns its id, passed into the compiled loop."""
        import tqdm

        bar = tqdm.tqdm(total=total, desc=description, unit="step", dynamic_ncols=True)
        with _LOCK:
            bar_id = next(_IDS)
            _BARS[bar_id] = bar
        return bar_id

    def close(self, bar_id: int):
        with _LOCK:
            bar = _BARS.pop(bar_id, None)
        if bar is not None:
            bar.close()

    def update(self, bar_id, offset, step, loss):
        """Called inside the loop: every `refresh_steps` steps, move the bar to
        `offset + step` and show `loss` (the smallest over vmapped starts)."""
        step_all = eqxi.unvmap_max(step)
        loss_all = -eqxi.unvmap_max(-jnp.where(jnp.isnan(loss), jnp.inf, loss))
        due = eqxi.nonbatchable(step_all % self.refresh_steps == 0)

        def show(bar_id, n, loss):
            with _LOCK:
                bar = _BARS.get(int(np.asarray(bar_id).reshape(-1)[0]))
            if bar is not None:
                bar.n = int(np.asarray(n).reshape(-1)[0])
                bar.set_postfix_str(f"loss {float(np.asarray(loss).reshape(-1)[0]):.6e}")

        jax.lax.cond(
            due,
            lambda: jax.debug.callback(show, bar_id, offset + step_all, loss_all),
            lambda: None,
        )


class NoProgress(eqx.Module):
    """No progress bar (the default of `fit`)."""

    def open(self, total: int, description: str = "fit") -> int:
        return 0

    def close(self, bar_id: int):
        pass

    def update(self, bar_id, offset, step, loss):
        pass
