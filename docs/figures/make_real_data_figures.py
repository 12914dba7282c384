"""Write the figures of docs/guides/real-data.md into docs/figures/ by running the
guide's own code (its python blocks, in order, with the working directory here).

Run: `python docs/figures/make_real_data_figures.py` (needs the cascaded-tanks data in
shared/data or $ONESHOT_JAX_DATA, and matplotlib). tests/test_docs.py runs the same
blocks, in a temporary folder.
"""

import os
import re
from pathlib import Path

import jax

HERE = Path(__file__).resolve().parent
GUIDE = HERE.parent / "guides" / "real-data.md"


def main():
    jax.config.update("jax_enable_x64", True)  # as the guides run (identification in float64)
    import matplotlib

    matplotlib.use("Agg")
    import oneshot_jax as oj

    blocks = re.findall(r"```python\n(.*?)```", GUIDE.read_text(), re.S)
    namespace = {"__name__": "__main__", "oj": oj}
    cwd = os.getcwd()
    os.chdir(HERE)
    try:
        for block in blocks:
            exec(compile(block, str(GUIDE), "exec"), namespace)
    finally:
        os.chdir(cwd)
    for name in sorted(set(re.findall(r'savefig\("([^"]+)"', GUIDE.read_text()))):
        print(HERE / name)


if __name__ == "__main__":
    main()
