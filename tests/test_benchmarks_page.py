"""The benchmarks page shows the stored runs as their scripts render them today.

docs/benchmarks.md cites `python benchmarks/<script>.py --render <json>...` for the tables of
runs kept in `benchmarks/gpu/` and `benchmarks/cpu/` (GPU runs cannot be repeated in CI):
each cited command is run, and every paragraph and table it prints must be on the page,
verbatim. A hand-edited table, or a render changed without the page, fails here.
"""

import contextlib
import io
import re
import runpy
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGE = (REPO / "docs" / "benchmarks.md").read_text()
CITED = re.findall(r"`python\s+(benchmarks/\w+\.py)\s+--render\s+([^`]+)`", PAGE)


def test_the_page_cites_render_commands():
    assert len(CITED) >= 6, CITED


def _render(script, files, monkeypatch):
    """What `python <script> --render <files>` prints, run in this process (a render
    reads JSON and prints: no process of its own, which cost each case a JAX import)."""
    monkeypatch.chdir(REPO)
    monkeypatch.setattr(sys, "argv", [script, "--render", *files.split()])
    monkeypatch.setattr(sys, "path", list(sys.path))  # (a script puts its folder first)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            runpy.run_path(str(REPO / script), run_name="__main__")
        except SystemExit as stop:
            assert stop.code in (None, 0), f"{script} exited with {stop.code}"
    return out.getvalue()


@pytest.mark.parametrize("script, files", CITED, ids=[f.split()[0] for _, f in CITED])
def test_rendered_runs_are_on_the_page_verbatim(script, files, monkeypatch):
    printed = _render(script, files, monkeypatch)
    blocks = [b.strip() for b in printed.split("\n\n") if b.strip()]
    assert blocks
    missing = [b for b in blocks if b not in PAGE]
    assert not missing, missing[0][:400]


def test_the_shown_command_keeps_its_closing_backtick():
    """`--json PATH` is dropped from the command the docs show, and only it: a command
    that ends with it keeps the code span's closing backtick and full stop."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        from timing import _shown
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    shown = _shown("Command: `python benchmarks/fit_strategy.py --nx 8 --json /tmp/a.json`.")
    assert shown == "Command: `python benchmarks/fit_strategy.py --nx 8`."
    assert _shown("`python b.py --json out.json --nx 2`.") == "`python b.py --nx 2`."
