"""The configuration schema of the experiments: dataclasses registered with Hydra's
ConfigStore, checked before anything runs.

Hydra checks the types when it composes the configuration (`seed=abc` is refused there,
naming the key). `load(cfg)` then builds these dataclasses (`OmegaConf.to_object`), whose
`__post_init__` checks the ranges and the consistency of the values (`experiment.T=0`,
`experiment.noise_std=-1`, an unknown method or a solver the experiment cannot run), so
a bad value is refused with a `ConfigError` naming it, before any data is generated.

The YAML files in `configs/` extend these schemas: `configs/config.yaml` starts from
`base_config`, `configs/experiment/<name>.yaml` from `/schema/experiment/<name>` and
`configs/solver/<name>.yaml` from `/schema/solver`. Physical constants default to the
example modules (`oneshot_jax.examples`), their one home.
"""

from __future__ import annotations

import dataclasses
import math
import string
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from oneshot_jax.examples import cascaded_tanks as tanks_example
from oneshot_jax.examples import emps as emps_example
from oneshot_jax.examples import satellite as sat

LIBRARY_SOLVERS = ("adam", "lbfgs", "gauss_newton", "levenberg_marquardt")
SOLVER_NAMES = (*LIBRARY_SOLVERS, "scipy")


class ConfigError(ValueError):
    """A configuration value out of its range, or values that do not fit together."""


# --------------------------------------------------------------------------- checks


def _fail(key, expected, value):
    raise ConfigError(f"`{key}` must be {expected}, got {value!r}.")


def _number(key, value, *, lo=None, hi=None, lo_open=False, hi_open=False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if not ok:
        parts = []
        if lo is not None:
            parts.append(f"{'>' if lo_open else '>='} {lo:g}")
        if hi is not None:
            parts.append(f"{'<' if hi_open else '<='} {hi:g}")
        _fail(key, "a finite number" + (" " + " and ".join(parts) if parts else ""), value)


def _integer(key, value, lo, hi=None, hi_name=None):
    """An integer in [lo, hi]; `hi_name`: the key `hi` comes from, named in the message."""
    top = "" if hi is None else f" and <= {hi}" + (f" ({hi_name})" if hi_name else "")
    if isinstance(value, bool) or not isinstance(value, int) or value < lo:
        _fail(key, f"an integer >= {lo}{top}", value)
    if hi is not None and value > hi:
        _fail(key, f"an integer >= {lo}{top}", value)


def _vector(key, value, n, *, positive=False):
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != n:
        _fail(key, f"a list of {n} numbers", value)
    for i, v in enumerate(value):
        _number(f"{key}[{i}]", v, lo=0.0 if positive else None, lo_open=positive)


def _one_of(key, value, options):
    if value not in options:
        _fail(key, "one of " + ", ".join(map(str, options)), value)


def _params(key, value, names, positive=()):
    if set(value) != set(names):
        _fail(key, f"a mapping with the keys {', '.join(names)}", value)
    for name in names:
        _number(
            f"{key}.{name}",
            value[name],
            lo=0.0 if name in positive else None,
            lo_open=name in positive,
        )


def _history(key, value):
    if isinstance(value, bool) or not isinstance(value, int) or value < 2 or value % 2:
        _fail(key, "an even integer >= 2", value)


def _emps_record(k, cfg):
    """The checks of the options every EMPS study shares (the model and the record)."""
    _number(k + "eps", cfg.eps, lo=0.0, lo_open=True)
    _integer(k + "substeps", cfg.substeps, 1)
    _integer(k + "velocity_halfwidth", cfg.velocity_halfwidth, 1)
    if cfg.n_samples is not None:
        _integer(k + "n_samples", cfg.n_samples, 4 * cfg.velocity_halfwidth)


# --------------------------------------------------------------------------- solver


@dataclass
class SolverConfig:
    """A solver spec `{name, label, kwargs}` (`configs/solver/*.yaml`, and the baselines
    of the satellite study). `name`: adam, lbfgs, gauss_newton, levenberg_marquardt (the
    library's solvers; `kwargs` are the solver object's options, see
    `experiments/common.py`) or scipy (`scipy.optimize.minimize` on the same cost)."""

    name: str = MISSING
    label: str | None = None
    kwargs: dict[str, Any] = field(default_factory=dict)

    def check(self, key: str = "solver") -> None:
        """Raise a `ConfigError` naming `key` (where this spec sits) if it cannot run."""
        from . import common

        _one_of(f"{key}.name", self.name, SOLVER_NAMES)
        try:
            common.check_solver(self.name, self.kwargs, key)
        except ValueError as err:
            raise ConfigError(str(err)) from None

    @property
    def title(self) -> str:
        """The label (`described`)."""
        return self.described(self.label)

    def described(self, label: str | None) -> str:
        """`label` (else the name); for a scipy baseline, the label its options make
        (`common.scipy_label`) where `label` does not name them all
        (`solver.kwargs.jac=fd` on `solver=slsqp` kept "closed-form gradient")."""
        if self.name != "scipy":
            return label or self.name
        from . import common

        words = common.scipy_words(self.kwargs)
        named = label is not None and all(w in label for w in words)
        return label if named else common.scipy_label(self.kwargs)


# --------------------------------------------------------------------------- satellite


@dataclass
class Fig2:
    pair: list[int] = field(default_factory=lambda: [0, 1])
    grid: int = 80
    margin: float = 0.15


@dataclass
class Fig3:
    n_starts: int = 5
    spread: float = 0.4


@dataclass
class Init:
    theta0: list[float] = field(default_factory=lambda: list(sat.THETA0))
    x0: Any = "first_sample"  # "first_sample" (z_0) or a list of 3 numbers


@dataclass
class Method:
    """A method of the satellite study: a solver on the multi-step cost C of eq. (5)
    ("multi_step", x0 estimated) or on the one-step prediction error ("single_step")."""

    label: str = MISSING
    cost: str = "multi_step"
    solver: SolverConfig = MISSING


@dataclass
class SatelliteConfig:
    """The satellite study of Section 4 (`experiments/satellite.py`)."""

    name: str = "satellite"
    dt: float = sat.DT
    T: int = 50
    theta_true: list[float] = field(default_factory=lambda: list(sat.THETA_TRUE))
    w0: list[float] = field(default_factory=lambda: list(sat.W0))
    torque_mean: float = sat.TORQUE_MEAN
    torque_std: float = sat.TORQUE_STD
    noise_std: float = sat.NOISE_STD
    data_substeps: int = 5
    model_substeps: int = 1
    theta_lower: float = 1e-12
    init: Init = field(default_factory=Init)
    n_seeds: int = 20
    horizons: list[int] = field(default_factory=lambda: [10, 20, 50, 100, 200, 500])
    horizon_seeds: int = 20
    simulate_time: float = 100.0
    figures: bool = True
    history: int = 2000
    fig2: Fig2 = field(default_factory=Fig2)
    fig3: Fig3 = field(default_factory=Fig3)
    solver_defaults: dict[str, dict[str, Any]] = field(default_factory=dict)
    methods: dict[str, Method] = field(default_factory=dict)
    run_methods: list[str] | None = None
    fig4_methods: list[str] = field(default_factory=list)
    fig5_methods: list[str] = field(default_factory=list)

    SOLVERS = SOLVER_NAMES

    def __post_init__(self):
        k = "experiment."
        _number(k + "dt", self.dt, lo=0.0, lo_open=True)
        _integer(k + "T", self.T, 2)
        _vector(k + "theta_true", self.theta_true, 3, positive=True)
        _vector(k + "w0", self.w0, 3)
        _number(k + "torque_mean", self.torque_mean)
        _number(k + "torque_std", self.torque_std, lo=0.0)
        # The Cramer-Rao bound (Figs. 5, 6, the tables) is sigma^2 (J^T J)^-1: it needs noise.
        _number(k + "noise_std", self.noise_std, lo=0.0, lo_open=True)
        _integer(k + "data_substeps", self.data_substeps, 1)
        _integer(k + "model_substeps", self.model_substeps, 1)
        _number(k + "theta_lower", self.theta_lower, lo=0.0, lo_open=True)
        _vector(k + "init.theta0", self.init.theta0, 3, positive=True)
        if self.theta_lower >= min(self.theta_true):
            # (every estimate would sit on the bound: the errors and the Cramer-Rao tables
            # would measure the bound, not the method)
            _fail(
                k + "theta_lower",
                f"below every entry of experiment.theta_true (the bound theta_i >= "
                f"theta_lower must keep the true values, the smallest {min(self.theta_true):g})",
                self.theta_lower,
            )
        if isinstance(self.init.x0, str):
            if self.init.x0 != "first_sample":
                _fail(k + "init.x0", "'first_sample' or a list of 3 numbers", self.init.x0)
        elif self.init.x0 is None or not hasattr(self.init.x0, "__len__"):
            _fail(k + "init.x0", "'first_sample' or a list of 3 numbers", self.init.x0)
        else:
            _vector(k + "init.x0", list(self.init.x0), 3)
        _integer(k + "n_seeds", self.n_seeds, 1)
        for i, h in enumerate(self.horizons):
            _integer(f"{k}horizons[{i}]", h, 2)
        _integer(k + "horizon_seeds", self.horizon_seeds, 0, hi=self.n_seeds, hi_name=k + "n_seeds")
        _number(k + "simulate_time", self.simulate_time, lo=self.dt)
        _history(k + "history", self.history)
        pair = list(self.fig2.pair)
        if len(pair) != 2 or len(set(pair)) != 2 or not set(pair) <= {0, 1, 2}:
            _fail(k + "fig2.pair", "two different indices among 0, 1, 2", pair)
        _integer(k + "fig2.grid", self.fig2.grid, 2)
        _number(k + "fig2.margin", self.fig2.margin, lo=0.0)
        _integer(k + "fig3.n_starts", self.fig3.n_starts, 1)
        _number(k + "fig3.spread", self.fig3.spread, lo=0.0, hi=1.0, hi_open=True)
        for key, m in self.methods.items():
            _one_of(f"{k}methods.{key}.cost", m.cost, ("multi_step", "single_step"))
            m.solver.check(f"{k}methods.{key}.solver")
        names = list(self.methods)
        for group in ("run_methods", "fig4_methods", "fig5_methods"):
            for key in getattr(self, group) or []:
                _one_of(f"{k}{group}", key, names)


# --------------------------------------------------------------------------- EMPS


@dataclass
class Windows:
    windows: list[int | None] = field(default_factory=list)


@dataclass
class EMPSConfig:
    """The EMPS study (`experiments/emps.py`)."""

    name: str = "emps"
    data_path: str | None = None
    eps: float = emps_example.EPS
    substeps: int = 1
    velocity_halfwidth: int = 5
    n_samples: int | None = None
    theta0: dict[str, float] = field(default_factory=lambda: dict(emps_example.THETA0))
    open_loop: Windows = field(default_factory=lambda: Windows([20, 50, 100, 200, 500, 2000]))
    closed_loop: Windows = field(default_factory=lambda: Windows([1000, 5000, None]))
    figures: bool = True
    check_unconstrained: bool = True
    history: int = 1000
    solver_defaults: dict[str, dict[str, Any]] = field(default_factory=dict)

    SOLVERS = LIBRARY_SOLVERS

    def __post_init__(self):
        k = "experiment."
        _emps_record(k, self)
        _params(k + "theta0", self.theta0, emps_example.PARAMS, positive=("M", "Fv", "Fc"))
        _history(k + "history", self.history)
        for fam in ("open_loop", "closed_loop"):
            wins = getattr(self, fam).windows
            if fam == "open_loop" and None in wins:
                _fail(k + "open_loop.windows", "window lengths (integers >= 2)", wins)
            for i, w in enumerate(wins):
                if w is not None:
                    _integer(f"{k}{fam}.windows[{i}]", w, 2)
        if not (self.open_loop.windows or self.closed_loop.windows):
            _fail(k + "open_loop.windows", "non-empty (or closed_loop.windows)", [])


@dataclass
class HybridAdam:
    """The joint Adam stage of the EMPS hybrid: `steps` (0 skips it), the peak rate of the
    cosine-decayed `lr` on theta, `lr_x0` on the windows' initial states, and
    `weight_decay` (0: none) on the network (`sparsity.l2`)."""

    steps: int = 200
    lr: float = 3e-3
    lr_x0: float = 1e-4
    weight_decay: float = 0.0


@dataclass
class EMPSHybridConfig:
    """The EMPS hybrid study: physics plus a neural friction term
    (`experiments/emps_hybrid.py`)."""

    name: str = "emps_hybrid"
    data_path: str | None = None
    eps: float = emps_example.EPS
    substeps: int = 1
    velocity_halfwidth: int = 5
    n_samples: int | None = None
    window: int = 50
    theta0: dict[str, float] = field(default_factory=lambda: dict(emps_example.THETA0))
    inputs: str = "v"
    widths: list[int] = field(default_factory=lambda: [8, 8])
    output_scale: float = 10.0
    seed: int = 0
    adam: HybridAdam = field(default_factory=HybridAdam)
    lm_steps: int = 100
    figures: bool = True
    history: int = 1000
    solver_defaults: dict[str, dict[str, Any]] = field(default_factory=dict)

    SOLVERS = LIBRARY_SOLVERS  # the physics stage's solver

    def __post_init__(self):
        k = "experiment."
        _emps_record(k, self)
        _integer(k + "window", self.window, 2)
        _params(k + "theta0", self.theta0, emps_example.PARAMS, positive=("M", "Fv", "Fc"))
        _one_of(k + "inputs", self.inputs, ("v", "qv"))
        for i, w in enumerate(self.widths):
            _integer(f"{k}widths[{i}]", w, 1)
        _number(k + "output_scale", self.output_scale, lo=0.0, lo_open=True)
        _integer(k + "seed", self.seed, 0)
        _integer(k + "adam.steps", self.adam.steps, 0)
        _number(k + "adam.lr", self.adam.lr, lo=0.0, lo_open=True)
        _number(k + "adam.lr_x0", self.adam.lr_x0, lo=0.0)
        _number(k + "adam.weight_decay", self.adam.weight_decay, lo=0.0)
        _integer(k + "lm_steps", self.lm_steps, 0)
        _history(k + "history", self.history)


@dataclass
class EMPSFrictionConfig:
    """The EMPS friction study: physical friction models trained for the open-loop
    protocol by horizon continuation (`experiments/emps_friction.py`)."""

    name: str = "emps_friction"
    data_path: str | None = None
    eps: float = emps_example.EPS
    substeps: int = 1
    velocity_halfwidth: int = 5
    n_samples: int | None = None
    windows: list[int] = field(default_factory=lambda: [50, 500, 5000])
    theta0: dict[str, float] = field(default_factory=lambda: dict(emps_example.THETA0))
    structures: list[str] = field(
        default_factory=lambda: [
            "coulomb_viscous",
            "asymmetric",
            "load",
            "stribeck",
            "load_stribeck",
            "position",
            "position_stribeck",
            "position_load_stribeck",
        ]
    )
    cv_holdouts: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.4, 0.5])
    stribeck_velocity: float = 0.01
    position_knots: int = 8  # knots of the position-dependent Coulomb friction and force
    solver_defaults: dict[str, dict[str, Any]] = field(default_factory=dict)

    SOLVERS = LIBRARY_SOLVERS

    def __post_init__(self):
        from . import emps_friction

        k = "experiment."
        _emps_record(k, self)
        if not self.windows:
            _fail(k + "windows", "a non-empty list of increasing window lengths", self.windows)
        for i, w in enumerate(self.windows):
            _integer(f"{k}windows[{i}]", w, 2)
        if any(b <= a for a, b in zip(self.windows, self.windows[1:])):
            _fail(k + "windows", "increasing", self.windows)
        _params(k + "theta0", self.theta0, emps_example.PARAMS, positive=("M", "Fv", "Fc"))
        if not self.structures:
            _fail(k + "structures", "a non-empty list", self.structures)
        for i, s in enumerate(self.structures):
            _one_of(f"{k}structures[{i}]", s, tuple(emps_friction.STRUCTURES))
        _number(k + "stribeck_velocity", self.stribeck_velocity, lo=0.0, lo_open=True)
        _integer(k + "position_knots", self.position_knots, 2)
        if not self.cv_holdouts:
            _fail(k + "cv_holdouts", "a non-empty list of held-out fractions", self.cv_holdouts)
        for i, h in enumerate(self.cv_holdouts):
            _number(f"{k}cv_holdouts[{i}]", h, lo=0.0, hi=0.9, lo_open=True)


# --------------------------------------------------------------------------- tanks


@dataclass
class TanksModel:
    substeps: int = 1
    theta0: dict[str, float] = field(default_factory=dict)


@dataclass
class OverflowModel(TanksModel):
    h1_starts: list[float] = field(default_factory=lambda: [5.0, 10.0, 15.0])


@dataclass
class TanksConfig:
    """The cascaded-tanks study (`experiments/cascaded_tanks.py`)."""

    name: str = "cascaded_tanks"
    data_path: str | None = None
    n_samples: int | None = None
    x0: list[float] = field(default_factory=lambda: [5.0, 5.0])
    gate_width: float = tanks_example.GATE_WIDTH
    relu_width: float = tanks_example.RELU_WIDTH
    basic: TanksModel = field(
        default_factory=lambda: TanksModel(2, {"k1": 0.05, "k3": 0.05, "k4": 0.03, "c": 0.0})
    )
    overflow: OverflowModel = field(
        default_factory=lambda: OverflowModel(4, {"h2": 10.0, "k5": 0.5}, [5.0, 10.0, 15.0])
    )
    # then the quadratic sensor (c2, from 0) beside the overflow model's estimate
    sensor: bool = True
    figures: bool = True
    history: int = 1000
    solver_defaults: dict[str, dict[str, Any]] = field(default_factory=dict)

    SOLVERS = LIBRARY_SOLVERS

    def __post_init__(self):
        k = "experiment."
        if self.n_samples is not None:
            _integer(k + "n_samples", self.n_samples, 10)
        _vector(k + "x0", self.x0, 2)
        _number(k + "gate_width", self.gate_width, lo=0.0, lo_open=True)
        _number(k + "relu_width", self.relu_width, lo=0.0, lo_open=True)
        _integer(k + "basic.substeps", self.basic.substeps, 1)
        _integer(k + "overflow.substeps", self.overflow.substeps, 1)
        _params(
            k + "basic.theta0",
            self.basic.theta0,
            ("k1", "k3", "k4", "c"),
            positive=("k1", "k3", "k4"),
        )
        _params(k + "overflow.theta0", self.overflow.theta0, ("h2", "k5"))
        _number(k + "overflow.theta0.k5", self.overflow.theta0["k5"], lo=0.0, hi=1.0)
        starts = self.overflow.h1_starts
        if not starts:
            _fail(k + "overflow.h1_starts", "a non-empty list of levels (V)", starts)
        for i, h in enumerate(starts):
            _number(f"{k}overflow.h1_starts[{i}]", h, lo=0.0)
        _history(k + "history", self.history)


@dataclass
class Residual:
    """The neural residual of the hybrid tanks model (`oneshot_jax.residual.MLP`)."""

    widths: list[int] = field(default_factory=lambda: [16, 16])
    inputs: str = "states"  # the features: (x1, x2), or "states_and_input": (x1, x2, u)
    n_starts: int = 3  # network initialisations (keys split from `seed`), in parallel
    # "best": the start of the lowest final Adam loss; "mean": a committee of all starts,
    # each refined, their protocol outputs averaged (needs n_starts > 1)
    combine: str = "mean"


@dataclass
class Joint:
    """The joint stage: Adam (cosine-decayed rate, optional weight decay on the network),
    then a refinement by another solver ("lbfgs", "levenberg_marquardt" or "none")."""

    adam_steps: int = 1000
    lr: float = 3e-3
    lr_x0: float = 1e-3
    weight_decay: float = 1e-4  # l2 on the network: less overfitting of the estimation record
    refine: str = "levenberg_marquardt"
    refine_steps: int = 30
    scale: str | None = None  # Adam(scale=...): None, or "theta0" (relative physical steps)
    holdout: float = 0.0  # fraction of the estimation record held out (its tail) to validate
    patience: int | None = None  # early stopping on the held-out tail (needs holdout > 0)


@dataclass
class TanksHybridConfig(TanksConfig):
    """The hybrid cascaded-tanks study (`experiments/cascaded_tanks_hybrid.py`): the
    overflow model of `TanksConfig` plus a neural residual on the level derivatives."""

    name: str = "cascaded_tanks_hybrid"
    substeps: int = 2
    residual: Residual = field(default_factory=Residual)
    joint: Joint = field(default_factory=Joint)
    extra_seeds: list[int] = field(default_factory=list)  # also train from these seeds

    def __post_init__(self):
        super().__post_init__()
        k = "experiment."
        _integer(k + "substeps", self.substeps, 1)
        for i, w in enumerate(self.residual.widths):
            _integer(f"{k}residual.widths[{i}]", w, 1)
        _one_of(k + "residual.inputs", self.residual.inputs, ("states_and_input", "states"))
        _integer(k + "residual.n_starts", self.residual.n_starts, 1)
        _one_of(k + "residual.combine", self.residual.combine, ("best", "mean"))
        if self.residual.combine == "mean" and self.residual.n_starts < 2:
            _fail(k + "residual.combine", "best with residual.n_starts = 1", "mean")
        _integer(k + "joint.adam_steps", self.joint.adam_steps, 1)
        _number(k + "joint.lr", self.joint.lr, lo=0.0, lo_open=True)
        _number(k + "joint.lr_x0", self.joint.lr_x0, lo=0.0)
        _number(k + "joint.weight_decay", self.joint.weight_decay, lo=0.0)
        _one_of(k + "joint.refine", self.joint.refine, ("lbfgs", "levenberg_marquardt", "none"))
        _integer(k + "joint.refine_steps", self.joint.refine_steps, 1)
        for i, seed in enumerate(self.extra_seeds):
            _integer(f"{k}extra_seeds[{i}]", seed, 0)
        if self.joint.scale is not None:
            _one_of(k + "joint.scale", self.joint.scale, ("theta0",))
            if self.joint.weight_decay > 0:
                _fail(k + "joint.scale", "null with joint.weight_decay > 0", self.joint.scale)
        _number(k + "joint.holdout", self.joint.holdout, lo=0.0, hi=0.5)
        if self.joint.patience is not None:
            _integer(k + "joint.patience", self.joint.patience, 1)
            if self.joint.holdout == 0:
                _fail(k + "joint.patience", "null unless joint.holdout > 0", self.joint.patience)


# --------------------------------------------------------------------------- top level


@dataclass
class Config:
    """The whole configuration (`configs/config.yaml`)."""

    experiment: Any = MISSING
    solver: SolverConfig = MISSING
    seed: int = 0
    publish: bool = False
    progress: bool = True  # progress bars on the long fits (EMPS, cascaded tanks)
    jax_cache_dir: str | None = None

    def __post_init__(self):
        _integer("seed", self.seed, 0)
        self.solver.check("solver")
        if not dataclasses.is_dataclass(self.experiment):  # (a YAML without a schema)
            raise ConfigError(
                "the experiment's configuration has no schema: its YAML in "
                "configs/experiment/ must start from one, `defaults: - "
                "/schema/experiment/<name>@experiment`, a dataclass registered in "
                "experiments/config.py's `register()` (see the experiments guide, 'An "
                "experiment of your own')."
            )
        allowed = type(self.experiment).SOLVERS
        if self.solver.name not in allowed:
            label = f" ({self.solver.label})" if self.solver.label else ""
            raise ConfigError(
                f"experiment={self.experiment.name} runs the library's solvers only "
                f"({', '.join(allowed)}); solver {self.solver.name!r}{label} is not supported. "
                f"Pick one of these, e.g. solver=levenberg_marquardt."
            )


# Characters kept in a sweep job's folder name (`swept`); any other becomes "-".
_NAME_CHARACTERS = frozenset(string.ascii_letters + string.digits + "._=,+-")
SWEPT_LENGTH = 120  # the longest suffix `swept` makes (a folder name holds 255 bytes)


def swept(overrides: str) -> str:
    """The suffix of a sweep job's folder (`hydra.sweep.subdir` in configs/config.yaml):
    the job's own overrides as Hydra joins them (`hydra.job.override_dirname`, less the
    keys the name already holds), `_seed=1,experiment.T=100`, or "" where there are
    none. A character that a folder name should not hold (`/`, a space, a bracket)
    becomes "-", and a suffix longer than `SWEPT_LENGTH` is cut there: the job's
    `.hydra/overrides.yaml` keeps them whole."""
    text = "".join(c if c in _NAME_CHARACTERS else "-" for c in str(overrides))
    return f"_{text[:SWEPT_LENGTH]}" if text else ""


def register() -> None:
    """Register the schemas with Hydra's ConfigStore, and the resolver `oj_swept`
    (`swept`) that names a sweep's folders (idempotent)."""
    if not OmegaConf.has_resolver("oj_swept"):
        OmegaConf.register_new_resolver("oj_swept", swept)
    cs = ConfigStore.instance()
    cs.store(name="base_config", node=Config)
    cs.store(group="schema/experiment", name="satellite", node=SatelliteConfig)
    cs.store(group="schema/experiment", name="emps", node=EMPSConfig)
    cs.store(group="schema/experiment", name="emps_hybrid", node=EMPSHybridConfig)
    cs.store(group="schema/experiment", name="emps_friction", node=EMPSFrictionConfig)
    cs.store(group="schema/experiment", name="cascaded_tanks", node=TanksConfig)
    cs.store(group="schema/experiment", name="cascaded_tanks_hybrid", node=TanksHybridConfig)
    cs.store(group="schema", name="solver", node=SolverConfig)


def load(cfg) -> Config:
    """The composed configuration as validated dataclasses (`ConfigError` on a bad value)."""
    try:
        out = OmegaConf.to_object(cfg)
    except OmegaConfBaseException as err:
        # OmegaConf wraps errors raised in __post_init__; show the original message.
        cause = err.__cause__ or err.__context__
        if isinstance(cause, (ValueError, TypeError)):
            raise ConfigError(str(cause)) from None
        raise ConfigError(str(err)) from err
    except (ValueError, TypeError) as err:
        raise ConfigError(str(err)) from None
    if not isinstance(out, Config) or not dataclasses.is_dataclass(out.experiment):
        raise ConfigError(
            "the configuration does not follow the schema of experiments/config.py "
            "(compose it from configs/config.yaml)."
        )
    _refuse_unknown_keys(cfg, out, "")
    _refuse_unread_solver_defaults(out.experiment)
    return out


def _solver_default_keys() -> dict[str, set[str]]:
    """{solver: options} that configs/solver/<solver>.yaml reads from
    `experiment.solver_defaults.<solver>.<option>`."""
    import re
    from pathlib import Path

    pattern = re.compile(r"experiment\.solver_defaults\.(\w+)\.(\w+)")
    keys: dict[str, set[str]] = {}
    for path in (Path(__file__).resolve().parent.parent / "configs" / "solver").glob("*.yaml"):
        for solver, option in pattern.findall(path.read_text()):
            keys.setdefault(solver, set()).add(option)
    return keys


def _refuse_unread_solver_defaults(experiment) -> None:
    """`+experiment.solver_defaults.adam.max_stepz=5` composes (an open dict) but no solver
    config reads it: refuse it, naming it."""
    known = _solver_default_keys()
    for solver, options in (getattr(experiment, "solver_defaults", None) or {}).items():
        where = f"experiment.solver_defaults.{solver}"
        if solver not in known:
            _fail(where, "one of " + ", ".join(sorted(known)), solver)
        unread = sorted(set(options or {}) - known[solver])
        if unread:
            raise ConfigError(
                f"unknown key(s) {', '.join(f'{where}.{o}' for o in unread)}: "
                f"configs/solver/ reads {', '.join(sorted(known[solver]))} from {where}."
            )


def _refuse_unknown_keys(node, obj, where):
    """A key that Hydra added (`+experiment.foo=1`) but the dataclass has no field for
    would be ignored: refuse it, naming it."""
    if not dataclasses.is_dataclass(obj) or not isinstance(node, DictConfig):
        return
    fields = {f.name for f in dataclasses.fields(obj)}
    unknown = sorted(str(k) for k in node.keys() if k not in fields)
    if unknown:
        raise ConfigError(
            f"unknown key(s) {', '.join(where + k for k in unknown)}: "
            f"{type(obj).__name__} has {', '.join(sorted(fields))}."
        )
    for name in fields & set(node.keys()):
        _refuse_unknown_keys(node[name], getattr(obj, name), f"{where}{name}.")


def as_dict(obj) -> Any:
    """A validated config (or part of it) as plain Python (for JSON and reports)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: as_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: as_dict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [as_dict(v) for v in obj]
    return obj
