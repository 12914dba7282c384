"""oneshot_jax: grey-box system identification with the one-shot closed-form gradient."""

from ._gradient import literal_value_and_grad as literal_value_and_grad
from ._gradient import value_and_grad as value_and_grad
from ._model import Model as Model
from ._simulate import loss as loss
from ._simulate import simulate as simulate

__version__ = "0.1.0"
