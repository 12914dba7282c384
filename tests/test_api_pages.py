"""The API reference is complete: every public function and class of the package and of its
public modules (their `__all__`) has a `:::` entry on a page of docs/api/, every public
method and property of a documented class is rendered (listed where the entry lists its
members, with a docstring), and the solvers' signatures show their defaults (the griffe
extension docs/griffe_equinox.py)."""

import inspect
import re
import types
from pathlib import Path

import pytest

import oneshot_jax as oj

ROOT = Path(__file__).resolve().parent.parent
API = ROOT / "docs" / "api"


def _entries():
    """`{path: members}` for every `::: path` of the API pages: the listed members, False
    for `members: false`, None where the page leaves the default (all documented ones)."""
    out = {}
    for page in sorted(API.glob("*.md")):
        text = page.read_text()
        for m in re.finditer(r"^::: (\S+)\n((?:    .*\n|\n)*)", text, re.M):
            options = m.group(2)
            if re.search(r"^\s+members: false", options, re.M):
                out[m.group(1)] = False
            elif listed := re.search(r"^\s+members:\n((?:\s+- \S+\n)+)", options, re.M):
                out[m.group(1)] = re.findall(r"- (\S+)", listed.group(1))
            else:
                out[m.group(1)] = None
    return out


ENTRIES = _entries()


def _documented(path: str) -> bool:
    if path in ENTRIES:
        return True
    parent, name = path.rsplit(".", 1)
    return isinstance(ENTRIES.get(parent), list) and name in ENTRIES[parent]


def _public_objects():
    """(path, object) of the package's public functions and classes."""
    out = []
    for name in dir(oj):
        obj = getattr(oj, name)
        if name.startswith("_"):
            continue
        if isinstance(obj, types.ModuleType):
            for sub in getattr(obj, "__all__", ()):
                value = getattr(obj, sub)
                if inspect.isclass(value) or inspect.isfunction(value):
                    out.append((f"oneshot_jax.{name}.{sub}", value))
        elif inspect.isclass(obj) or callable(obj):
            out.append((f"oneshot_jax.{name}", obj))
    return out


PUBLIC = _public_objects()


@pytest.mark.parametrize("path", [p for p, _ in PUBLIC])
def test_every_public_name_has_an_entry(path):
    assert _documented(path), f"{path} is on no page of docs/api/"


def _inherited_from_a_documented_base(cls, name):
    """A method that implements an interface documented on its base (the solvers' init,
    step, ... on `AbstractSolver`)."""
    return any(
        name in vars(base) and _documented(f"oneshot_jax.{base.__name__}")
        for base in cls.__mro__[1:]
    )


def _methods():
    out = []
    for path, cls in PUBLIC:
        if not inspect.isclass(cls) or ENTRIES.get(path) is False:
            continue
        for name, value in vars(cls).items():
            if name.startswith("_") or not (
                callable(value) or isinstance(value, (property, classmethod, staticmethod))
            ):
                continue
            if not _inherited_from_a_documented_base(cls, name):
                out.append((path, name, value))
    return out


@pytest.mark.parametrize(
    "path, name, value", _methods(), ids=[f"{p}.{n}" for p, n, _ in _methods()]
)
def test_every_public_method_is_rendered(path, name, value):
    members = ENTRIES.get(path)
    if isinstance(members, list):
        assert name in members, f"{path}.{name} is not in the members listed for {path}"
    func = value.fget if isinstance(value, property) else getattr(value, "__func__", value)
    assert inspect.getdoc(func), f"{path}.{name} has no docstring (mkdocstrings hides it)"


def test_the_solvers_signatures_show_their_defaults():
    griffe = pytest.importorskip("griffe")
    extension = griffe.load_extensions(f"{ROOT / 'docs' / 'griffe_equinox.py'}:EquinoxSignatures")
    package = griffe.load("oneshot_jax", extensions=extension, resolve_aliases=True)
    for name in ("LevenbergMarquardt", "GaussNewton", "Adam", "LBFGS", "Optax", "Optimistix"):
        init = package[name].members["__init__"]
        solver = getattr(oj, name)
        expected = {
            p.name: p.default
            for p in inspect.signature(solver).parameters.values()
            if p.default is not p.empty
        }
        shown = {p.name: p.default for p in init.parameters if p.name != "self"}
        assert expected and {k: shown[k] for k in expected} == {
            k: repr(v) for k, v in expected.items()
        }
    assert str(package["LevenbergMarquardt"].members["__init__"].parameters["gtol"].default) == (
        "1e-08"
    )
    # Result containers are not constructed by users: no signature.
    assert "__init__" not in package["FitResult"].members
