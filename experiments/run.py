"""Hydra entry point for the experiments (configs in ../configs).

    python experiments/run.py                                   # experiment=satellite solver=adam
    python experiments/run.py solver=gauss_newton experiment.T=100 seed=3
    python experiments/run.py -m solver=adam,gauss_newton seed=0,1
    python experiments/run.py publish=true                      # also refresh the README material

The experiment module `experiments/<experiment.name>.py` must expose
`run(cfg, outdir: pathlib.Path) -> dict`. This script enables float64, writes
`resolved_config.yaml` (Hydra keeps its own copy under `.hydra/`), calls `run`, and writes
the returned dict to `results.json` in the run's output folder. With `publish=true` the
run's `results.md` is copied to `experiments/<name>_results.md` (figure links rewritten to
`../docs/figures/`) and the figures named in `results["figures"]` to
`docs/figures/<name>_<figure>`.
"""

from __future__ import annotations

import importlib
import json
import shutil
import sys
import time
from pathlib import Path

import hydra
import jax
from omegaconf import DictConfig, OmegaConf

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

# Identification runs in float64; the library never enables it itself.
jax.config.update("jax_enable_x64", True)


def _setup_cache(cache_dir):
    if cache_dir:
        path = Path(str(cache_dir)).expanduser()
        path.mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def publish(name: str, outdir: Path, figures) -> list[Path]:
    """Copy a run's results.md and figures into the repository (README material)."""
    written = []
    fig_dir = REPO / "docs" / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    md = (outdir / "results.md").read_text() if (outdir / "results.md").exists() else None
    for fig in figures or []:
        target = fig_dir / f"{name}_{fig}"
        shutil.copyfile(outdir / fig, target)
        written.append(target)
        if md is not None:
            md = md.replace(f"]({fig})", f"](../docs/figures/{name}_{fig})")
    if md is not None:
        target = REPO / "experiments" / f"{name}_results.md"
        target.write_text(md)
        written.append(target)
    return written


def execute(cfg: DictConfig, outdir: Path) -> dict:
    """Run `cfg.experiment.name` into `outdir` and write the run's files."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    _setup_cache(cfg.get("jax_cache_dir"))
    (outdir / "resolved_config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    name = cfg.experiment.name
    module = importlib.import_module(f"experiments.{name}")
    t0 = time.perf_counter()
    results = module.run(cfg, outdir)
    results = dict(results)
    results.setdefault("wall_time_s", time.perf_counter() - t0)
    (outdir / "results.json").write_text(json.dumps(results, indent=2, allow_nan=False))
    if cfg.get("publish", False):
        for path in publish(name, outdir, results.get("figures")):
            print(f"published {path.relative_to(REPO)}")
    print(f"{name}: results in {outdir} ({results['wall_time_s']:.1f} s)")
    return results


def task(cfg: DictConfig) -> None:
    """The Hydra task: run the configured experiment into Hydra's output folder."""
    from hydra.core.hydra_config import HydraConfig

    execute(cfg, Path(HydraConfig.get().runtime.output_dir))


# An absolute config path, so that the same entry point works as a script and when
# imported by the `oneshot-jax` console script (oneshot_jax/_cli.py).
main = hydra.main(version_base="1.3", config_path=str(REPO / "configs"), config_name="config")(task)


if __name__ == "__main__":
    main()
