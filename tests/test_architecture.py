"""The package's layering (docs/architecture.md), checked on the source.

- The import graph of `oneshot_jax` has no cycle. Every module of the package is parsed,
  and every import it holds counts: at the top, under a condition, and
  inside a function. `from . import x` and `from .x import y` are resolved to modules (`y`
  may be a submodule or a name), and importing `a.b.c` also runs the packages `a.b` and
  `a` above it.
- The layer table of docs/architecture.md holds: every module of the package has a row
  (or its package, named as a folder, has one), and no import goes from a module to one
  of a higher layer.
- No function-local import of the package inside the package, except the documented
  ones of `LAZY`, which load something on first use and are left out of the graph.
- `import oneshot_jax` loads neither the example models nor matplotlib.
- `tests/`, `benchmarks/`, `experiments/` and the scripts of `docs/` import no private
  module: only the public API and `oneshot_jax.internal`.
"""

import ast
import importlib.util
import pkgutil
import re
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import NamedTuple

import pytest

import oneshot_jax

PACKAGE = "oneshot_jax"
PACKAGE_DIR = Path(oneshot_jax.__file__).resolve().parent
ROOT = PACKAGE_DIR.parent

# Function-local imports kept on purpose: (importing module, imported module) -> why.
# They run on first use, not when the module is imported, so they are no edge of the
# import graph (diffrax keeps such imports of `_integrate` in `_adjoint.py`).
LAZY = {
    ("oneshot_jax", "oneshot_jax.examples"): (
        "`oneshot_jax.__getattr__` loads the example models on first use of `oj.examples` "
        "(PEP 562): they are written against the public API, so they sit above the "
        "package's `__init__`, and programs that do not use them do not load them."
    ),
}

# removed by issue 20 branches; must be empty at merge
# Accepted exceptions: import cycles (as the frozenset of modules each one joins) and
# function-local imports (as (module, function, imported module)). None today; an entry
# that no longer occurs fails the tests too.
KNOWN: set = set()

# Folders whose Python files use only the public API and `oneshot_jax.internal`.
CLIENTS = ("tests", "benchmarks", "experiments", "docs")
CLIENTS_EXCEPT = {"tests/test_architecture.py"}  # reads the package's modules by name


# --------------------------------------------------------------------------- the graph


def package_modules() -> dict[str, Path]:
    """Every module of the package (packages included) and its file."""
    out = {PACKAGE: PACKAGE_DIR / "__init__.py"}
    for info in pkgutil.walk_packages([str(PACKAGE_DIR)], PACKAGE + "."):
        out[info.name] = Path(importlib.util.find_spec(info.name).origin)
    return out


class Import(NamedTuple):
    """One import statement (or `importlib.import_module("...")` call) of a module."""

    module: str  # the importing module
    targets: list  # the modules it names
    function: str | None  # the enclosing function's qualified name, or None
    line: int


def _names(node, module, is_package, modules):
    """The dotted modules an import node names, resolved against `modules`."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom):
        if node.level:
            parts = module.split(".")
            if not is_package:
                parts = parts[:-1]
            parts = parts[: len(parts) - (node.level - 1)]
            base = ".".join([*parts, *([node.module] if node.module else [])])
        else:
            base = node.module or ""
        return [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
    if (  # importlib.import_module("a.b")
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "import_module"
        and node.args
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    ):
        return [node.args[0].value]
    return []


def _nearest(name, modules):
    """`name` if it is a module, else the nearest package above it that is one."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(module, path, modules) -> list[Import]:
    """The package-internal imports of one module, with the function each sits in."""
    is_package = path.name == "__init__.py"
    out = []

    def visit(node, scope, function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                inner = [*scope, child.name]
                is_function = not isinstance(child, ast.ClassDef)
                visit(child, inner, ".".join(inner) if is_function else function)
                continue
            if isinstance(child, ast.Lambda):
                visit(child, scope, function or ".".join([*scope, "<lambda>"]))
                continue
            names = _names(child, module, is_package, modules)
            targets = [_nearest(n, modules) for n in names if n.split(".")[0] == PACKAGE]
            if targets:
                out.append(Import(module, [t for t in targets if t], function, child.lineno))
            visit(child, scope, function)

    visit(ast.parse(path.read_text(), str(path)), [], None)
    return out


def _ancestors(name):
    parts = name.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))}


def import_graph(modules=None):
    """`(graph, local)`: the graph maps each module to the modules importing it runs
    (lazy imports of `LAZY` left out; a submodule's packages added); `local` lists the
    function-local imports as (module, function, imported module)."""
    modules = package_modules() if modules is None else modules
    graph = {m: set() for m in modules}
    local = set()
    for module, path in modules.items():
        for imp in imports_of(module, path, modules):
            for target in imp.targets:
                if imp.function is not None:
                    if (module, target) in LAZY:
                        continue
                    local.add((module, imp.function, target))
                # `import a.b.c` runs a, a.b and a.b.c too; the packages above `module`
                # itself are already running when it is imported.
                implied = _ancestors(target) - _ancestors(module)
                graph[module] |= {target, *implied} - {module}
    return graph, local


def components(graph) -> list[list[str]]:
    """The import cycles of `graph` ({node: nodes it imports}) as its strongly connected
    components of more than one node, each the sorted list of its nodes (Tarjan's
    algorithm, iterative)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return sorted(found)


def cycle_through(component, graph):
    """One cycle of a component, for the message: the shortest closed path of `graph`
    from `component[0]` back to it (breadth-first, within the component)."""
    first, members = component[0], set(component)
    parent = {}
    frontier = [first]
    while frontier:
        following = []
        for node in frontier:
            for child in sorted(graph.get(node, ())):
                if child == first:
                    path = [node]
                    while path[-1] != first:
                        path.append(parent[path[-1]])
                    return [*reversed(path), first]
                if child in members and child not in parent:
                    parent[child] = node
                    following.append(child)
        frontier = following
    raise AssertionError(f"{component} is not strongly connected")


# --------------------------------------------------------------------------- the finder


def test_cycle_finder_on_small_graphs():
    assert components({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    assert components({"a": {"a"}}) == []  # a module importing a name of its own
    assert components({"a": {"b"}, "b": {"a"}}) == [["a", "b"]]
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": {"e"}, "e": {"d"}, "f": {"a"}}
    assert components(graph) == [["a", "b", "c"], ["d", "e"]]
    assert cycle_through(["a", "b", "c"], graph) == ["a", "b", "c", "a"]
    # two cycles through "a" make one component; the message shows the shorter
    graph = {"a": {"b", "x"}, "b": {"c"}, "c": {"a"}, "x": {"y"}, "y": {"z"}, "z": {"a"}}
    assert components(graph) == [["a", "b", "c", "x", "y", "z"]]
    assert cycle_through(components(graph)[0], graph) == ["a", "b", "c", "a"]
    # a long chain (no recursion limit) closed at its end
    chain = {i: {i + 1} for i in range(5000)}
    assert components(chain) == []
    chain[5000] = {0}
    assert len(components(chain)[0]) == 5001


def test_new_cycles_fail(tmp_path):
    """A package with a top-level and a function-local import that close a cycle, and
    an import of a submodule that runs its package: the graph has all three edges."""
    pkg = tmp_path / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "from . import a as a\n",
        "a.py": "from .b import thing\n",
        "b.py": "def thing():\n    from . import a\n\n    return a\n",
        "c.py": "from oneshot_jax.sub.d import y\n",
        "sub/__init__.py": "from .. import c\n",
        "sub/d.py": "y = 1\n",
    }
    modules = {}
    for name, text in files.items():
        (pkg / name).write_text(text)
        dotted = ".".join([PACKAGE, *Path(name).with_suffix("").parts])
        modules[dotted.removesuffix(".__init__")] = pkg / name
    graph, local = import_graph(modules)
    assert local == {("oneshot_jax.b", "thing", "oneshot_jax.a")}
    assert graph["oneshot_jax.c"] == {"oneshot_jax.sub", "oneshot_jax.sub.d"}
    assert components(graph) == [
        ["oneshot_jax.a", "oneshot_jax.b"],
        ["oneshot_jax.c", "oneshot_jax.sub"],
    ]


# --------------------------------------------------------------------------- the package


GRAPH, LOCAL = import_graph()


def test_the_graph_covers_the_package():
    assert {"oneshot_jax._fit", "oneshot_jax.datasets._files", "oneshot_jax.examples"} <= set(GRAPH)
    assert "oneshot_jax" in GRAPH["oneshot_jax.examples.satellite"]
    assert "oneshot_jax.datasets._locations" in GRAPH["oneshot_jax.datasets._files"]


def test_no_import_cycle():
    found = {frozenset(c): c for c in components(GRAPH)}
    new = [
        f"{_explain(cycle_through(c, GRAPH))}  (the cycle joins {', '.join(c)})"
        for key, c in found.items()
        if key not in KNOWN
    ]
    assert not new, "import cycles (`->` an import, `⇢` one inside a function):\n" + "\n".join(new)
    gone = [sorted(k) for k in KNOWN if isinstance(k, frozenset) and k not in found]
    assert not gone, f"these cycles are gone: remove them from KNOWN: {gone}"


def _explain(cycle):
    local = {(m, t) for m, _, t in LOCAL}
    out = cycle[0]
    for a, b in zip(cycle, cycle[1:]):
        out += f" {'⇢' if (a, b) in local else '->'} {b}"
    return out


def test_no_function_local_import():
    known = {k for k in KNOWN if isinstance(k, tuple)}
    new = sorted(LOCAL - known)
    assert not new, (
        "function-local imports inside the package (import at the top of the module; "
        "if that makes a cycle, the code is in the wrong layer: see docs/architecture.md):\n"
        + "\n".join(f"{m}: in {f}: {t}" for m, f, t in new)
    )
    gone = sorted(known - LOCAL)
    assert not gone, f"these function-local imports are gone: remove them from KNOWN: {gone}"


def test_lazy_imports_are_there():
    found = set()
    for module, path in package_modules().items():
        for imp in imports_of(module, path, GRAPH):
            found |= {(module, t) for t in imp.targets if imp.function is not None}
    assert set(LAZY) <= found, f"LAZY lists imports that are gone: {set(LAZY) - found}"


def test_nothing_in_the_package_imports_internal():
    users = sorted(m for m, targets in GRAPH.items() if "oneshot_jax.internal" in targets)
    assert not users, f"oneshot_jax.internal is for tests, benchmarks and experiments: {users}"


def direct_warnings(source: str) -> list[int]:
    """The lines of `source` that call `warnings.warn` (or `warn` imported from warnings)."""
    tree = ast.parse(source)
    names = {
        a.asname or a.name
        for n in ast.walk(tree)
        if isinstance(n, ast.ImportFrom) and n.module == "warnings"
        for a in n.names
        if a.name == "warn"
    }
    return [
        n.lineno
        for n in ast.walk(tree)
        if isinstance(n, ast.Call)
        and (
            (
                isinstance(n.func, ast.Attribute)
                and n.func.attr == "warn"
                and getattr(n.func.value, "id", None) == "warnings"
            )
            or (isinstance(n.func, ast.Name) and n.func.id in names)
        )
    ]


def test_the_direct_warning_finder():
    assert direct_warnings("import warnings\nwarnings.warn('a')\n") == [2]
    assert direct_warnings("from warnings import warn as w\nw('a')\n") == [2]
    assert direct_warnings("from ._caller_warnings import warn\nwarn('a')\n") == []


def test_every_warning_goes_through_the_recorded_warn():
    """The package warns through `_caller_warnings.warn` only, so that `fit` keeps every
    warning of its run in `FitResult.warnings` (`at_caller` raises again warnings that
    were recorded where they were first raised)."""
    found = {
        module: lines
        for module, path in package_modules().items()
        if module != "oneshot_jax._caller_warnings" and (lines := direct_warnings(path.read_text()))
    }
    assert not found, f"warnings.warn called directly (use _caller_warnings.warn): {found}"
    # (and no module that imports it hides it behind a local name: a parameter `warn=True`
    # of `clip_x0` made every x0 start outside its bounds fail with "'bool' object is not
    # callable")
    hidden = {}
    for module, path in package_modules().items():
        tree = ast.parse(path.read_text())
        if not any(
            isinstance(n, ast.ImportFrom) and any(a.name == "warn" for a in n.names)
            for n in ast.walk(tree)
        ):
            continue
        lines = [
            n.lineno
            for n in ast.walk(tree)
            if (isinstance(n, ast.arg) and n.arg == "warn")
            or (isinstance(n, ast.Name) and n.id == "warn" and isinstance(n.ctx, ast.Store))
        ]
        if lines:
            hidden[module] = lines
    assert not hidden, f"a local name `warn` hides the imported function: {hidden}"


def test_import_loads_neither_the_examples_nor_matplotlib():
    code = (
        "import sys, oneshot_jax\n"
        "print(sorted(m for m in sys.modules if m.startswith(('oneshot_jax.examples', "
        "'matplotlib'))))\n"
        "print(oneshot_jax.examples.satellite.__name__)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.splitlines()
    assert out == ["[]", "oneshot_jax.examples.satellite"]


# --------------------------------------------------------------------------- the layers


ARCHITECTURE = ROOT / "docs" / "architecture.md"


def _module_of(cell_name):
    """The dotted module a file name of the table names (`_fit.py`, `_solver/base.py`,
    `__init__.py`), or the package a folder names (`datasets/`)."""
    path = cell_name.removesuffix("/").removesuffix(".py").removesuffix("__init__")
    return ".".join([PACKAGE, *(p for p in path.split("/") if p)])


def layer_table(text):
    """`(modules, packages)` of the layer table of docs/architecture.md: the layer number
    of each module of a row (one or several per cell, in backticks), and of each package
    named as a folder (`datasets/`), which covers its modules not listed themselves."""
    modules, packages, layer = {}, {}, None
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) != 4 or not cells[1].startswith("`"):
            continue
        number = re.match(r"(\d+)\.", cells[0])
        layer = int(number.group(1)) if number else layer
        for name in re.findall(r"`([^`]+)`", cells[1]):
            into = packages if name.endswith("/") else modules
            into[_module_of(name)] = layer
    return modules, packages


def layer_of(module, modules, packages):
    """The layer of `module`: its own row, else the row of the nearest package above it
    named as a folder; None if the table has neither."""
    if module in modules:
        return modules[module]
    name = module
    while name:
        if name in packages:
            return packages[name]
        name = name.rpartition(".")[0]
    return None


def test_the_layer_table_parser():
    text = (
        "| Layer | Module | Role | What it holds |\n"
        "| --- | --- | --- | --- |\n"
        "| 1. Base | `a.py` | a | `x`, `y`. |\n"
        "| | `sub/` | sub | `sub/c.py`. |\n"
        "| 2. Top | `b.py`, `sub/d.py` | b, d | `z`. |\n"
        "| | `__init__.py` | api | |\n"
    )
    modules, packages = layer_table(text)
    assert modules == {
        "oneshot_jax.a": 1,
        "oneshot_jax.b": 2,
        "oneshot_jax.sub.d": 2,
        "oneshot_jax": 2,
    }
    assert packages == {"oneshot_jax.sub": 1}
    assert layer_of("oneshot_jax.sub.c", modules, packages) == 1
    assert layer_of("oneshot_jax.sub.d", modules, packages) == 2
    assert layer_of("oneshot_jax.e", modules, packages) is None


def test_the_layer_table_holds():
    """Every module of the package has a row of the table of docs/architecture.md (or
    its package does), and every import goes to a module of its own layer or below (the
    lazy import of `LAZY` is no edge of GRAPH)."""
    modules, packages = layer_table(ARCHITECTURE.read_text())
    missing = sorted(m for m in GRAPH if layer_of(m, modules, packages) is None)
    assert not missing, f"modules missing from the layer table of docs/architecture.md: {missing}"
    upward = [
        f"{m} (layer {layer_of(m, modules, packages)}) -> {t} "
        f"(layer {layer_of(t, modules, packages)})"
        for m in sorted(GRAPH)
        for t in sorted(GRAPH[m])
        if layer_of(t, modules, packages) > layer_of(m, modules, packages)
    ]
    assert not upward, "imports from a lower layer to a higher one:\n" + "\n".join(upward)


# --------------------------------------------------------------------------- the clients


def _private(dotted):
    """Whether a dotted name under the package passes through a private part."""
    parts = dotted.split(".")
    return parts[0] == PACKAGE and any(p.startswith("_") and not p.startswith("__") for p in parts)


def _private_imports(tree):
    """(line, what) for each import of a private module or name of the package, and
    each attribute path through one (`oj._pytree`), in `tree` and in the code of its
    string constants (scripts run in a subprocess)."""
    out = []
    aliases = {}  # local name -> the package module it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if _private(a.name):
                    out.append((node.lineno, f"import {a.name}"))
                if a.name.split(".")[0] == PACKAGE:
                    aliases[a.asname or a.name.split(".")[0]] = a.name if a.asname else PACKAGE
        elif isinstance(node, ast.ImportFrom) and not node.level:
            for a in node.names:
                dotted = f"{node.module}.{a.name}"
                if _private(dotted):
                    out.append((node.lineno, f"from {node.module} import {a.name}"))
                elif (node.module or "").split(".")[0] == PACKAGE:
                    aliases[a.asname or a.name] = dotted
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if "import" in node.value and PACKAGE in node.value:
                try:
                    inner = ast.parse(textwrap.dedent(node.value))
                except SyntaxError:
                    continue
                out += [(node.lineno + line - 1, what) for line, what in _private_imports(inner)]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(f"{PACKAGE}.{node.attr}"):
            chain, value = [node.attr], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if isinstance(value, ast.Name) and value.id in aliases:
                dotted = ".".join([aliases[value.id], *reversed(chain)])
                if _private(dotted):
                    out.append((node.lineno, dotted))
    return sorted(set(out))


def test_the_private_import_finder():
    code = (
        "import oneshot_jax as oj\n"
        "from oneshot_jax import _checks, fit\n"
        "from oneshot_jax._pytree import flat_host\n"
        "from oneshot_jax.datasets import _download\n"
        "from oneshot_jax.internal import flat_host\n"
        "import oneshot_jax._fit\n"
        "x = oj._pytree.flat_host(oj.fit)\n"
        "S = '''\n    from oneshot_jax._cost import Cost\n'''\n"
    )
    assert [what for _, what in _private_imports(ast.parse(code))] == [
        "from oneshot_jax import _checks",
        "from oneshot_jax._pytree import flat_host",
        "from oneshot_jax.datasets import _download",
        "import oneshot_jax._fit",
        "oneshot_jax._pytree",
        "from oneshot_jax._cost import Cost",
    ]


def _client_files():
    for folder in CLIENTS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            relative = path.relative_to(ROOT).as_posix()
            if relative not in CLIENTS_EXCEPT and "site" not in path.relative_to(ROOT).parts:
                yield relative, path


@pytest.mark.parametrize("relative", [r for r, _ in _client_files()])
def test_clients_import_no_private_module(relative):
    found = _private_imports(ast.parse((ROOT / relative).read_text(), relative))
    assert not found, (
        f"{relative} reaches into private modules (use the public API, or add the name to "
        "oneshot_jax/internal.py):\n" + "\n".join(f"  line {n}: {what}" for n, what in found)
    )
