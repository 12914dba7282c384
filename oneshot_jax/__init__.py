"""oneshot_jax: grey-box system identification with the one-shot closed-form gradient."""

import importlib as _importlib

from . import constraints as constraints
from . import datasets as datasets
from . import metrics as metrics
from . import penalties as penalties
from . import plot as plot
from . import residual as residual
from . import sharding as sharding
from . import sparsity as sparsity
from ._aggregate import Aggregate as Aggregate
from ._ahead import AheadPrediction as AheadPrediction
from ._ahead import ProcessNoise as ProcessNoise
from ._ahead import estimate_process_noise as estimate_process_noise
from ._ahead import predict_ahead as predict_ahead
from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._continuation import BasinCheck as BasinCheck
from ._continuation import Continuation as Continuation
from ._continuation import Stage as Stage
from ._continuation import check_basin as check_basin
from ._continuation import fit_continuation as fit_continuation
from ._covariance import NeweyWest as NeweyWest
from ._delta import Derived as Derived
from ._discretisation import DiscretisationCheck as DiscretisationCheck
from ._discretisation import check_discretisation as check_discretisation
from ._fit import fit as fit
from ._fit_result import FitHistory as FitHistory
from ._fit_result import FitResult as FitResult
from ._fit_result import Starts as Starts
from ._fit_result import load_result as load_result
from ._gradient import literal_value_and_grad as literal_value_and_grad
from ._gradient import value_and_grad as value_and_grad
from ._identifiable import Orthogonal as Orthogonal
from ._identifiable import PhysicsFirst as PhysicsFirst
from ._identifiable import Round as Round
from ._identifiable import fit_orthogonal as fit_orthogonal
from ._identifiable import fit_physics_first as fit_physics_first
from ._initial_state import Prediction as Prediction
from ._initial_state import X0Estimate as X0Estimate
from ._initial_state import estimate_x0 as estimate_x0
from ._initial_state import predict as predict
from ._io import save_result as save_result
from ._model import Model as Model
from ._model import ode_step as ode_step
from ._operating_point import Equilibrium as Equilibrium
from ._operating_point import LinearModel as LinearModel
from ._operating_point import find_equilibrium as find_equilibrium
from ._operating_point import linearise as linearise
from ._progress import NoProgress as NoProgress
from ._progress import TqdmProgress as TqdmProgress
from ._results import RESULTS as RESULTS
from ._simulate import loss as loss
from ._simulate import simulate as simulate
from ._solver import LBFGS as LBFGS
from ._solver import AbstractSolver as AbstractSolver
from ._solver import Adam as Adam
from ._solver import GaussNewton as GaussNewton
from ._solver import LevenbergMarquardt as LevenbergMarquardt
from ._solver import Optax as Optax
from ._solver import Optimistix as Optimistix
from ._stability import Stability as Stability
from ._stability import check_stability as check_stability
from ._strategy import VJP as VJP
from ._strategy import AbstractStrategy as AbstractStrategy
from ._strategy import Auto as Auto
from ._strategy import Jacobian as Jacobian
from ._strategy import ParallelInTime as ParallelInTime
from ._validation import Validation as Validation
from ._windows import Windows as Windows
from ._x0_smoother import KalmanPath as KalmanPath

__version__ = "0.2.0"


def __getattr__(name):
    """`oneshot_jax.examples` on first use (PEP 562). The example models are written
    against the public API above (`import oneshot_jax as oj`), so they sit above this
    module: importing them here would be an import cycle, and would load them into every
    program that imports the library."""
    if name == "examples":
        return _importlib.import_module("oneshot_jax.examples")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted({*globals(), "examples"})
