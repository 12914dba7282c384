"""`oneshot-jax`: the console script, the same as `python experiments/run.py`.

    oneshot-jax                                    # experiment=satellite solver=adam
    oneshot-jax solver=gauss_newton experiment.T=100 seed=3
    oneshot-jax -m solver=adam,levenberg_marquardt

The experiments and their Hydra configs live next to the package in a source checkout
(`experiments/` and `configs/` beside `oneshot_jax/`), so the script works from a source
checkout or an editable install (`pip install -e .`), not from a wheel.
"""

from __future__ import annotations

import sys
from pathlib import Path


def _repo_root() -> Path:
    root = Path(__file__).resolve().parent.parent
    needed = (root / "experiments" / "run.py", root / "configs" / "config.yaml")
    if not all(path.is_file() for path in needed):
        raise SystemExit(
            "oneshot-jax: experiments/run.py and configs/ were not found next to the installed "
            f"package ({root}). The console script needs a source checkout installed with "
            "`pip install -e .`; from a checkout you can also run `python experiments/run.py`."
        )
    return root


def main() -> None:
    root = _repo_root()
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from experiments.run import main as hydra_main

    hydra_main()


if __name__ == "__main__":
    main()
