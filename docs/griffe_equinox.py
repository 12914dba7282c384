"""A griffe extension for the API pages: the signature, with its defaults, of the
equinox modules that a user constructs with options (the solvers, the progress meters).

equinox writes a module's `__init__` from its fields when the class is created, so the
source that griffe reads has none, and mkdocstrings shows no signature. This extension
imports such a class and gives it an `__init__` with the signature Python reports
(`inspect.signature`), e.g. `LevenbergMarquardt(rtol=0.0, atol=0.0, gtol=1e-08, ...)`.
Result containers (`FitResult`, ...), which a user does not construct, are left alone.

mkdocs.yml loads it: `extensions: [docs/griffe_equinox.py:EquinoxSignatures]`.
"""

from __future__ import annotations

import inspect

import equinox as eqx
import griffe

_KINDS = {
    inspect.Parameter.POSITIONAL_ONLY: griffe.ParameterKind.positional_only,
    inspect.Parameter.POSITIONAL_OR_KEYWORD: griffe.ParameterKind.positional_or_keyword,
    inspect.Parameter.VAR_POSITIONAL: griffe.ParameterKind.var_positional,
    inspect.Parameter.KEYWORD_ONLY: griffe.ParameterKind.keyword_only,
    inspect.Parameter.VAR_KEYWORD: griffe.ParameterKind.var_keyword,
}


def _constructed_with_options(obj) -> bool:
    """A public equinox module a user builds from options: a solver of `fit`, or a
    module whose every field has a default (a progress meter)."""
    from oneshot_jax import AbstractSolver

    if not (isinstance(obj, type) and issubclass(obj, eqx.Module)):
        return False
    if obj.__name__.startswith(("Abstract", "_")):
        return False
    params = inspect.signature(obj).parameters.values()
    return issubclass(obj, AbstractSolver) or all(p.default is not p.empty for p in params)


class EquinoxSignatures(griffe.Extension):
    """Give the option-holding equinox modules of oneshot_jax their signatures."""

    def on_class(self, *, cls: griffe.Class, **kwargs) -> None:
        if "__init__" in cls.members or not cls.path.startswith("oneshot_jax"):
            return
        try:
            obj = griffe.dynamic_import(cls.path)
        except ImportError:
            return
        if not _constructed_with_options(obj):
            return
        params = [
            griffe.Parameter(
                p.name,
                kind=_KINDS[p.kind],
                default=None if p.default is p.empty else repr(p.default),
            )
            for p in inspect.signature(obj).parameters.values()
        ]
        init = griffe.Function(
            "__init__",
            lineno=0,
            endlineno=0,
            parent=cls,
            parameters=griffe.Parameters(griffe.Parameter("self"), *params),
            returns="None",
        )
        cls.set_member("__init__", init)
