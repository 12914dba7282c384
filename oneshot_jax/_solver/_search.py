"""The globalisations of the least-squares step (`least_squares`): a search decides whether
the step of the linearisation is taken, and owns its state.

- `Backtracking` (`GaussNewton`): alpha = 1, 1/2, ... along the projection arc
  P(theta + alpha h) until the loss decreases; no state, no damping.
- `NielsenDamping` (`LevenbergMarquardt`): a trust region by the damping mu of the step
  (J^T J + mu D) h = -J^T r, adapted by Nielsen's rule; its state is (mu, nu).

A search answers `damping(state)` (the mu of the next step) and `search(...)` (the
outcome, `Trial`, and its next state). A rejected step is followed by the
projected-gradient step of `least_squares`, whatever the search.
"""

import abc
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._problem import Params


class Trial(NamedTuple):
    """The outcome of a search: the new point, its loss, whether it was accepted and
    whether the search gave up."""

    params: Params
    loss: jax.Array
    accept: jax.Array
    gave_up: jax.Array
    at_full: jax.Array  # whether the point is the full step's (`full`), accepted


class AbstractSearch(eqx.Module):
    """A globalisation of the least-squares step (see the module docstring)."""

    @abc.abstractmethod
    def init(self, dtype) -> Any:
        """The search's state at the start."""

    @abc.abstractmethod
    def damping(self, state) -> jax.Array | float:
        """The damping mu of the next step (0 for an undamped Gauss-Newton step)."""

    @abc.abstractmethod
    def search(self, trial, C, step, full, pred, state) -> tuple[Trial, Any]:
        """Globalise `step` from the current point of loss `C`.

        **Arguments:**

        - `trial`: alpha -> (params + alpha step projected, its loss).
        - `C`: the loss at the current point.
        - `step`: the step h (`Params`).
        - `full`: `trial(1.0)`, the full projected step and its loss.
        - `pred`: the decrease of C the linear model predicts for the full step.
        - `state`: the search's state.

        **Returns:** the `Trial` and the search's next state.
        """


class Backtracking(AbstractSearch):
    """Halve alpha = 1, 1/2, ... down to 2^-30 until the loss decreases (a non-finite
    trial loss counts as no decrease); gives up when it does not."""

    def init(self, dtype):
        return ()

    def damping(self, state):
        return 0.0

    def search(self, trial, C, step, full, pred, state):
        del step, pred

        def cond(c):
            return (c[2] >= C) & (c[0] > 2.0**-30)

        def body(c):
            alpha = c[0] / 2
            return alpha, *trial(alpha)

        alpha, new, Cn = jax.lax.while_loop(cond, body, (jnp.array(1.0, C.dtype), *full))
        accept = Cn < C
        return Trial(new, Cn, accept, ~accept, accept & (alpha == 1.0)), state


class Damping(NamedTuple):
    mu: jax.Array  # damping
    nu: jax.Array  # Nielsen's damping growth


class NielsenDamping(AbstractSearch):
    """Levenberg-Marquardt's trust region by damping. The full step is accepted when it
    decreases the loss with rho = actual / predicted decrease > 0; then
    mu *= max(1/3, 1 - (2 rho - 1)^3), nu = 2, else mu *= nu, nu *= 2 (Nielsen,
    "Damping parameter in Marquardt's method", 1999). A non-finite trial loss is a
    rejected step. Gives up when mu passes 1e20."""

    mu0: float

    def init(self, dtype):
        return Damping(jnp.array(self.mu0, dtype), jnp.array(2.0, dtype))

    def damping(self, state):
        return state.mu

    def search(self, trial, C, step, full, pred, state):
        del trial, step
        mu, nu = state
        new, Cn = full
        rho = (C - Cn) / jnp.where(pred > 0, pred, jnp.inf)
        accept = (Cn < C) & (rho > 0)
        mu_new = jnp.where(accept, mu * jnp.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), mu * nu)
        nu_new = jnp.where(accept, 2.0, 2.0 * nu)
        return Trial(new, Cn, accept, mu_new > 1e20, accept), Damping(mu_new, nu_new)
