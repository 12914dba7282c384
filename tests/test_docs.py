"""The documentation runs: README's quick start and the code of the getting-started page
and the guides execute as pasted, and every public name has a page in the API reference."""

import re
from pathlib import Path

import pytest

import oneshot_jax as oj

ROOT = Path(__file__).resolve().parent.parent
GUIDES = [
    "docs/getting-started.md",
    "docs/guides/solvers.md",
    "docs/guides/constraints.md",
    "docs/guides/fixed-and-x0.md",
    "docs/guides/data.md",
    "docs/guides/uncertainty.md",
    "docs/guides/parallel.md",
    "docs/guides/real-data.md",
    "docs/guides/hybrid.md",
]


def _blocks(path):
    text = (ROOT / path).read_text()
    return re.findall(r"```python\n(.*?)```", text, re.S)


def _run(paths, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__main__"}
    for path in paths:
        blocks = _blocks(path)
        assert blocks, f"{path} has no python code"
        for block in blocks:
            exec(compile(block, str(ROOT / path), "exec"), namespace)
    return namespace


def test_readme_quick_start_runs(tmp_path, monkeypatch):
    ns = _run(["README.md"], tmp_path, monkeypatch)
    assert ns["result"].success
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150


def test_getting_started_and_guides_run(tmp_path, monkeypatch):
    ns = _run(GUIDES, tmp_path, monkeypatch)
    assert ns["result"].success and ns["again"].loss == ns["result"].loss


def _public_names():
    names = set()
    for name in dir(oj):
        if name.startswith("_"):
            continue
        obj = getattr(oj, name)
        if getattr(obj, "__module__", "").startswith("oneshot_jax") or callable(obj):
            names.add(name)
    return names


@pytest.mark.parametrize("name", sorted(_public_names()))
def test_every_public_name_is_in_the_api_reference(name):
    api = "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    module = getattr(oj, name)
    if isinstance(module, type(oj)):  # a public module: its page documents it
        assert f"::: oneshot_jax.{name}" in api, name
    else:
        assert f"::: oneshot_jax.{name}\n" in api, name
