"""Config-driven experiments for oneshot_jax (Hydra entry point: `experiments/run.py`).

Each experiment is a module `experiments/<name>.py` exposing `run(cfg, outdir) -> dict`,
selected by `cfg.experiment.name`; `experiments/common.py` holds the solver dispatch that
experiments share (library solvers and scipy baselines from one `{name, kwargs}` spec).
"""
