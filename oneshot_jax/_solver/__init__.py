from .base import AbstractSolver as AbstractSolver
from .gauss_newton import GaussNewton as GaussNewton
from .levenberg_marquardt import LevenbergMarquardt as LevenbergMarquardt
from .optax import LBFGS as LBFGS
from .optax import Adam as Adam
from .optax import Optax as Optax
from .optimistix import Optimistix as Optimistix
