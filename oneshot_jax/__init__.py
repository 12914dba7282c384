"""oneshot_jax: grey-box system identification with the one-shot closed-form gradient."""

from . import constraints as constraints
from . import datasets as datasets
from . import metrics as metrics
from ._fit import FitResult as FitResult
from ._fit import fit as fit
from ._gradient import literal_value_and_grad as literal_value_and_grad
from ._gradient import value_and_grad as value_and_grad
from ._model import Model as Model
from ._model import ode_step as ode_step
from ._simulate import loss as loss
from ._simulate import simulate as simulate
from ._solvers import StopReason as StopReason
from ._solvers import adam as adam

__version__ = "0.1.0"
