"""Config-driven experiments for oneshot_jax (Hydra entry point: `experiments/run.py`, or
`python -m experiments`).

Each experiment is a module `experiments/<name>.py` exposing `run(cfg, outdir, command)
-> dict`, selected by `cfg.experiment.name`; `experiments/config.py` is the configuration
schema (types, ranges, defaults) and `experiments/common.py` the solver dispatch that the
experiments share (library solvers and scipy baselines from one `{name, kwargs}` spec).
The models are `oneshot_jax.examples`.
"""
