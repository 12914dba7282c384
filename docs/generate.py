"""Write the generated parts of the documentation: the output of the quick start
(`docs/snippets/quickstart.py`, README's quick start) that the home page shows, in
`docs/snippets/quickstart.txt`, what the first code block of each page in
`PAGE_OUTPUTS` prints (`print(result)` on the getting-started page), in the snippet named
there, and the conditions they were printed under (`docs/snippets/output-conditions.md`).

    python docs/generate.py

`tests/test_docs.py` runs the quick start and those blocks and checks that the stored
outputs are what they print (up to the wall time and the last digits of the numbers).
"""

from __future__ import annotations

import contextlib
import io
import math
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SNIPPETS = REPO / "docs" / "snippets"
QUICK_START = SNIPPETS / "quickstart.py"
QUICK_START_OUTPUT = SNIPPETS / "quickstart.txt"
# The conditions the stored outputs were printed under (their wall times are that
# machine's), a sentence the pages include after them.
CONDITIONS = SNIPPETS / "output-conditions.md"

# Pages whose first ```python block prints a result, and the snippet of its output that
# the page includes (`--8<-- "<name>"` in a ```text block after the code).
PAGE_OUTPUTS = {
    "docs/getting-started.md": SNIPPETS / "getting-started.txt",
    "docs/guides/non-uniform.md": SNIPPETS / "non-uniform.txt",
}

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_WALL = re.compile(r"in [\d.]+ s \(wall")


def run_quick_start() -> str:
    """What the quick start prints, run in this process."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(QUICK_START.read_text(), str(QUICK_START), "exec"), {"__name__": "__main__"})
    return out.getvalue()


def run_first_block(page: str) -> str:
    """What the first ```python block of `page` (a path from the repository root) prints,
    run in this process."""
    (code, *_) = re.findall(r"```python\n(.*?)```", (REPO / page).read_text(), re.S)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, page, "exec"), {"__name__": "__main__"})
    return out.getvalue()


def same_output(a: str, b: str, rtol: float = 1e-3, atol: float = 1e-10) -> bool:
    """Whether two printed outputs agree: the same text, with the wall time ignored and
    the other numbers equal to `rtol` or `atol` (the last digits, and numbers at the
    level of rounding errors, may differ between machines)."""
    a, b = _WALL.sub("in _ s (wall", a), _WALL.sub("in _ s (wall", b)
    if _NUMBER.sub("#", a).split() != _NUMBER.sub("#", b).split():
        return False
    xs, ys = _NUMBER.findall(a), _NUMBER.findall(b)
    return all(math.isclose(float(x), float(y), rel_tol=rtol, abs_tol=atol) for x, y in zip(xs, ys))


def conditions() -> str:
    """The sentence of `CONDITIONS`: hardware, versions and commit (`benchmarks/timing.py`)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from timing import conditions as measured

    return (
        "The output above is that of a first call: its wall time includes compiling the "
        "fit. " + measured(argv=["docs/generate.py"]) + "\n"
    )


def main() -> None:
    sys.path.insert(0, str(REPO))  # the package of this checkout
    CONDITIONS.write_text(conditions())
    text = run_quick_start()
    QUICK_START_OUTPUT.write_text(text)
    print(f"wrote {QUICK_START_OUTPUT}:\n{text}")
    for page, snippet in PAGE_OUTPUTS.items():
        text = run_first_block(page)
        snippet.write_text(text)
        print(f"wrote {snippet} ({page}):\n{text}")


if __name__ == "__main__":
    main()
