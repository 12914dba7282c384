"""The `solver=` argument of `fit` and `estimate_x0`: names, solver objects, optax
transforms, optimistix solvers and sequences of them, as a tuple of solver objects."""

import functools

import optax
import optimistix as optx

from ._solver import (
    LBFGS,
    Adam,
    GaussNewton,
    LevenbergMarquardt,
    Optax,
    Optimistix,
)
from ._solver.base import AbstractSolver

SOLVER_ALIASES = {
    "adam": Adam,
    "lbfgs": LBFGS,
    "gauss_newton": GaussNewton,
    "levenberg_marquardt": LevenbergMarquardt,
}


@functools.cache
def _default_solver(name):
    """The solver a name stands for, with its default settings (made once: solvers are
    immutable)."""
    return SOLVER_ALIASES[name]()


def as_solvers(solver) -> tuple:
    """`solver` as a tuple of solver objects (strings are aliases of default objects;
    optax transforms and optimistix solvers are wrapped)."""
    if isinstance(solver, optax.GradientTransformation):
        return (Optax(solver),)
    if isinstance(solver, (list, tuple)):
        if not solver:
            raise ValueError("`solver` is an empty sequence; give at least one solver.")
        # (a nested sequence is flattened: `[Adam(), [LBFGS(), LevenbergMarquardt()]]` runs
        # all three, it does not drop the inner sequence's later solvers)
        return tuple(one for s in solver for one in as_solvers(s))
    if isinstance(solver, str):
        if solver not in SOLVER_ALIASES:
            raise ValueError(
                f"unknown `solver` {solver!r}; valid names are {', '.join(SOLVER_ALIASES)}, "
                "or pass a solver object (oneshot_jax.GaussNewton(...), Adam(...), ...)."
            )
        return (_default_solver(solver),)
    if isinstance(solver, AbstractSolver):
        return (solver,)
    if isinstance(solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)):
        return (Optimistix(solver),)
    if hasattr(solver, "init") and hasattr(solver, "update") and callable(solver.update):
        return (Optax(solver),)
    raise TypeError(
        f"`solver` must be one of {', '.join(SOLVER_ALIASES)}, a oneshot_jax solver object, "
        f"an optax.GradientTransformation, an optimistix solver, or a sequence of these; "
        f"got {solver!r}."
    )
