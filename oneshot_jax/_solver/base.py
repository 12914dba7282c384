"""The interface every solver of `fit` implements, and the pieces they share.

A solver is an equinox Module holding its options. `fit` runs it through one loop
(`oneshot_jax._iterate`):

    state = solver.init(problem, params)
    while not solver.terminate(problem, params, state)[0] and step < solver.max_steps:
        params, state = solver.step(problem, params, state)
    params, loss, blocks = solver.postprocess(problem, params, state, result)

`summary(state)` gives the loss C and the gradient norm at the current `params`, which the
loop records in the history and shows on a progress bar. A new solver is one file that
implements these methods, plus a test.
"""

import abc
import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._optimality import Measures, no_measures
from .._problem import FitProblem, Params


class AbstractSolver(eqx.Module):
    """Base class of the solvers of `fit`: an equinox Module whose fields are its
    options (a `max_steps` among them), with the methods `init`, `step`, `terminate` and
    `summary` (and optionally `postprocess`, `measures`, `check_regulariser`,
    `check_dtype`), which `fit`'s one loop calls (this module's docstring). They see the
    `FitProblem` (`value_and_grad`, `residuals`, `jacobian`, `feasible` for the
    constraints) and the free variables `Params(theta, x0)`, a named tuple of theta's free
    entries (p,) and each trajectory's free initial-state entries (N, m).

    A solver's `converged` is taken as it says where its `measures` give the first-order
    measure it tested (the library's solvers); without them `fit` measures the returned
    point itself, against the solver's `gtol` (1e-8 without one), and reports a claim
    that does not hold as `stalled`. The solvers guide has an example (gradient descent).
    """

    max_steps: eqx.AbstractVar[int]

    # Whether `init` leaves the evaluation at the starting point to the first `step`
    # (a priming step that keeps params): the loop (`oneshot_jax._iterate`) then runs
    # that step before it tests or counts anything, and the compiled program holds one
    # copy of the evaluation (the linearisation of the least-squares solvers), not two.
    primes_in_step = False  # (a class constant: no annotation, so not a field)

    # The options that enter the compiled solve only in comparisons and as the starting
    # value of a state (no Python branch, no static field and no arithmetic of the
    # iterates depends on them, so the iterates are the same to the last bit):
    # `traced_options` passes them as arrays, so that a new tolerance reuses the compiled
    # fit instead of compiling again. (A learning rate enters the arithmetic, where a
    # traced value rounds differently from a constant: it stays static.)
    TRACED_OPTIONS = ()  # (a class constant: no annotation, so not a field)
    # Integer options traced as int32 (the library's solvers: `max_steps`, which enters
    # the loop's bound alone and the progress bar's offsets, so that a new budget reuses
    # the compiled fit where the history buffer keeps its rows, `fit`'s default
    # `history`, 1000 rows, for every budget). Empty here: a solver of one's own may use
    # its `max_steps` as a Python number (a static field, a shape).
    TRACED_INTEGERS = ()
    # Whether a positive gtol counts as at least `_optimality.resolution` (the first-order
    # solvers: they have no stall after which the round-off limit would apply).
    GTOL_AT_LEAST_RESOLUTION = False

    def traced_options(self, dtype) -> "AbstractSolver":
        """This solver with the `TRACED_OPTIONS` that hold Python numbers as 0-d arrays of
        `dtype` (the data's: what a Python number would have become in the arithmetic),
        which the compiled call takes as traced arguments rather than as part of its
        static key."""
        names = [
            n
            for n in self.TRACED_OPTIONS
            if isinstance(getattr(self, n), (int, float, np.integer, np.floating))
            and not isinstance(getattr(self, n), (bool, np.bool_))
        ]
        counts = [
            n
            for n in self.TRACED_INTEGERS
            if isinstance(getattr(self, n, None), (int, np.integer))
            and not isinstance(getattr(self, n), (bool, np.bool_))
            and 0 <= getattr(self, n) <= np.iinfo(np.int32).max
        ]
        if not names and not counts:
            return self
        return eqx.tree_at(
            lambda s: [getattr(s, n) for n in names + counts],
            self,
            [np.asarray(getattr(self, n), dtype) for n in names]
            + [np.asarray(getattr(self, n), np.int32) for n in counts],
        )

    @abc.abstractmethod
    def init(self, problem: FitProblem, params: Params) -> Any:
        """The solver's state at the starting point (evaluating whatever it needs there,
        or with `primes_in_step` a placeholder that the first `step` fills in)."""

    @abc.abstractmethod
    def step(self, problem: FitProblem, params: Params, state) -> tuple[Params, Any]:
        """One iteration: the next iterate and state."""

    @abc.abstractmethod
    def terminate(self, problem: FitProblem, params: Params, state) -> tuple[jax.Array, Any]:
        """Whether to stop at `params`, and the `RESULTS` item saying why."""

    @abc.abstractmethod
    def summary(self, state) -> tuple[jax.Array, jax.Array]:
        """(C, ||grad C||) at the current iterate (NaN where the solver has no gradient)."""

    def check_regulariser(self, regulariser) -> None:
        """Raise a ValueError unless this solver can minimise C + g with the non-smooth
        regulariser g (a `sparsity.ProximalTransformation`) given in `fit(regulariser=...)`.
        Only the proximal first-order solvers (`Adam`, `Optax`) can."""
        del regulariser
        name = type(self).__name__
        raise ValueError(
            f"`{name}` cannot minimise C + g with a proximal regulariser (l1, group_lasso, "
            "l2) in `regulariser`: it needs a smooth sum of squares or loss. Select the terms "
            "with a proximal solver: oneshot_jax.Adam (proximal Adam, exact zeros) or "
            "oneshot_jax.Optax(transform) with the regulariser's learning_rate; then refit "
            f"the surviving terms without the regulariser, e.g. with `{name}` and "
            "fixed=oneshot_jax.sparsity.fixed_zeros(result.theta, where)."
        )

    def check_dtype(self, dtype) -> None:
        """Raise a ValueError if this solver cannot run on data of `dtype` (the problem's
        floating dtype) under JAX's present configuration. The library's solvers run in
        float32 and float64 alike."""
        del dtype

    def measures(self, state) -> Measures:
        """The quantities the last stop was tested on (`oneshot_jax._optimality.Measures`):
        the first-order measure at the current iterate, the last step's scaled size and
        its predicted relative decrease (NaN where the solver has none)."""
        return no_measures(self.summary(state)[0].dtype)

    def postprocess(self, problem: FitProblem, params: Params, state, result):
        """The point to return, its loss, and the normal-equation blocks (C, A, B, C_i) of
        the data residuals at it when the solver holds them (else None: the covariance
        evaluates the Jacobian itself)."""
        del problem, result
        return params, self.summary(state)[0], None

    def __repr__(self) -> str:
        # Every option with its value (equinox's repr hides those left at their defaults),
        # on one line; a wrapped transform, solver or schedule is named briefly.
        options = ", ".join(
            f"{f.name}={brief(getattr(self, f.name))}" for f in dataclasses.fields(self) if f.repr
        )
        return f"{type(self).__name__}({options})"

    def settings(self) -> dict:
        """The options, for `FitResult.solver` and saved results (JSON-friendly)."""
        out = {"solver": type(self).__name__}
        for name, value in ((f.name, getattr(self, f.name)) for f in dataclasses.fields(self)):
            if isinstance(value, np.generic):  # (a NumPy scalar option, np.float32(1e-6))
                value = value.item()
            if isinstance(value, (bool, int, float, str)) or value is None:
                out[name] = value
            else:
                out[name] = repr(value)
        return out


def grad_norm(g: Params):
    return jnp.sqrt(jnp.sum(g.theta**2) + jnp.sum(g.x0**2))


def check_options(solver, *, positive=(), non_negative=(), integers=(), fractions=()):
    """ValueErrors naming the option, for a solver's __check_init__ (`fractions`: in
    [0, 1), as Adam's decay rates and `gtol`, a bound on a cosine that 1 would meet at the
    start)."""
    name = type(solver).__name__
    for field in integers:
        v = getattr(solver, field)
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ValueError(f"`{name}({field}=...)` must be a non-negative integer, got {v!r}.")
        if v > 2**31 - 1:  # (the compiled loops count in int32: a larger budget wraps)
            raise ValueError(f"`{name}({field}=...)` must be at most 2**31 - 1, got {v!r}.")
    for field in fractions:
        v = getattr(solver, field)
        if not is_real(v) or not 0 <= v < 1:
            raise ValueError(f"`{name}({field}=...)` must be a number in [0, 1), got {v!r}.")
    for field in positive:
        v = getattr(solver, field)
        if not is_real(v) or not v > 0:
            raise ValueError(f"`{name}({field}=...)` must be a positive finite number, got {v!r}.")
    for field in non_negative:
        v = getattr(solver, field)
        if not is_real(v) or not v >= 0:
            raise ValueError(f"`{name}({field}=...)` must be a finite number >= 0, got {v!r}.")


def is_real(v):
    """A finite real number (not a bool, NaN or inf): a Python or NumPy scalar."""
    return (
        isinstance(v, (int, float, np.integer, np.floating))
        and not isinstance(v, (bool, np.bool_))
        and math.isfinite(v)
    )


def brief(value) -> str:
    """A solver option in a few characters: numbers and strings as Python writes them, an
    optimistix solver by its name and numeric options, an optax transform by its type, a
    function (a learning-rate schedule) by its name."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, (bool, int, float, str)) or value is None:
        return repr(value)
    if isinstance(value, eqx.Module):
        prefix = "optx." if type(value).__module__.startswith("optimistix") else ""
        scalars = ((f.name, getattr(value, f.name)) for f in dataclasses.fields(value) if f.repr)
        options = ", ".join(
            f"{k}={v!r}" for k, v in scalars if isinstance(v, (bool, int, float, str))
        )
        return f"{prefix}{type(value).__name__}({options})"
    if hasattr(value, "init") and hasattr(value, "update"):
        return f"<optax.{type(value).__name__}>"
    if callable(value):
        name = getattr(value, "__qualname__", type(value).__name__)
        return f"<function {name.split('.<locals>')[0]}>"
    return repr(value)
