"""The `solver=` argument of `fit` and `estimate_x0`: names, solver objects, optax
transforms, optimistix solvers and sequences of them, as a tuple of solver objects."""

import dataclasses
import functools
import inspect

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


def _options_of(cls) -> frozenset:
    return frozenset(f.name for f in dataclasses.fields(cls) if not f.name.startswith("_"))


@functools.cache
def _solver_options() -> dict:
    """Each option of the library's solver classes, with the classes that take it."""
    classes = (LevenbergMarquardt, GaussNewton, LBFGS, Adam, Optax, Optimistix)
    options = {}
    for cls in classes:
        for name in _options_of(cls):
            options.setdefault(name, []).append(cls.__name__)
    return options


def takes_solver_options(fn):
    """`fn` (`fit`), whose keywords that it does not take but a solver does (`max_steps`,
    `gtol`, ...: `nlgreyestOptions` sets them on the estimation) raise a TypeError that
    says where they go, the solver object; other unknown keywords raise Python's own."""
    known = frozenset(inspect.signature(fn).parameters)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if not known.issuperset(kwargs):
            options = _solver_options()
            theirs = sorted(k for k in kwargs if k not in known and k in options)
            if theirs:
                takers = options[theirs[0]]
                others = sorted(k for k in kwargs if k not in known and k not in options)
                raise TypeError(
                    f"`{fn.__name__}` got {theirs}, options of a solver, not of "
                    f"`{fn.__name__}`: give them to the solver object, e.g. "
                    f"`solver=oneshot_jax.{takers[0]}({theirs[0]}=...)` "
                    f"({', '.join(takers)} take `{theirs[0]}`)"
                    + (f"; {others} neither takes." if others else ".")
                )
        return fn(*args, **kwargs)

    return call
