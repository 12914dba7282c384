"""What the repository's benchmarks, experiments and tests use beyond the public API.

The public API is what `oneshot_jax` and its public modules export (`oneshot_jax.fit`,
`oneshot_jax.constraints`, ...; see the API reference). The benchmarks, the experiments
and the tests also need a few pieces below it: the cost bundle and the problem a solver
sees, the sequential and parallel kernels they time or check against each other, the
host-side pytree helpers, caches and thresholds. They import them from here, never from
a private module (`oneshot_jax._x`), so that code inside the package can move without
touching them: a move changes one line of this file. `tests/test_architecture.py`
checks that no file of `tests/`, `benchmarks/`, `experiments/` or `docs/` imports a
private module.

Nothing here is a stable interface for users: names may change or go in any release.

One line per name, sorted by the module that defines it. A name that is private where
it is defined (`_name`) is exported under a public, descriptive name. The modules at the
end are for tests that replace one of a module's globals (`monkeypatch.setattr(module,
name, value)`), which needs the module itself.
"""

from . import _zero_gradient as zero_gradient_checks  # noqa: F401  (its memory cap)
from ._aggregate import augment as aggregate_augment  # noqa: F401
from ._checks import _STRUCTURE as CHECK_DATA_STRUCTURES  # noqa: F401
from ._checks import check_cost as check_cost
from ._checks import check_data as check_data
from ._checks import fixed_mask as fixed_mask
from ._continuation import _window_states as continuation_window_states  # noqa: F401
from ._cost import Cost as Cost
from ._cost import Mask as Mask
from ._covariance import covariance as covariance
from ._fit import _theta_order as kept_theta_order  # noqa: F401
from ._fit_report import theta_order as theta_order
from ._gradient import value_and_grad_impl as value_and_grad_impl
from ._gradient import value_and_grad_of_states as value_and_grad_of_states
from ._identifiable import _augmented as orthogonal_model  # noqa: F401
from ._identifiable import _basis as orthogonal_basis  # noqa: F401
from ._identifiable import _orthonormal as orthonormal_basis  # noqa: F401
from ._io import replaced as replace_atomically  # noqa: F401
from ._linalg import eliminate_x0 as eliminate_x0
from ._linalg import identifiable as identifiable
from ._linalg import normal_blocks as normal_blocks
from ._linalg import schur_complement as schur_complement
from ._optimality import check_first_order as check_first_order
from ._optimality import data_scale as data_scale
from ._optimality import first_order as first_order
from ._optimality import scaling as scaling
from ._optimality import stall_test as stall_test
from ._optimality import standard_errors as standard_errors
from ._parallel import METHOD_NAMES as METHOD_NAMES
from ._parallel import diagonal_linear_recurrence as diagonal_linear_recurrence
from ._parallel import linear_recurrence as linear_recurrence
from ._parallel import matrix_linear_recurrence as matrix_linear_recurrence
from ._parallel import newton_rollout as newton_rollout
from ._parallel import reverse_diagonal_linear_recurrence as reverse_diagonal_linear_recurrence
from ._parallel import reverse_linear_recurrence as reverse_linear_recurrence
from ._parallel._elk import diagonal_elk_increment as diagonal_elk_increment
from ._parallel._elk import elk_increment as elk_increment
from ._parallel._rollout import DAMPED as DAMPED
from ._parallel._rollout import NEWTON as NEWTON
from ._parallel._rollout import SEQUENTIAL as SEQUENTIAL
from ._problem import FitProblem as FitProblem
from ._problem import Params as Params
from ._problem import Regulariser as Regulariser
from ._pytree import build as build
from ._pytree import flat_host as flat_host
from ._pytree import pack as pack
from ._pytree import unflatten_rows as unflatten_rows
from ._pytree import unpack as unpack
from ._results import _BY_NAME as RESULTS_BY_NAME  # noqa: F401
from ._sensitivity import trajectory_jacobian as trajectory_jacobian
from ._simulate import rollout as rollout
from ._solver._linearisation import DIAG_PROBES as DIAG_PROBES
from ._solver._linearisation import DenseLinearisation as DenseLinearisation
from ._solver._linearisation import linearise as linearise
from ._solver._linearisation import placeholder as placeholder
from ._solver._search import Backtracking as Backtracking
from ._solver._search import Damping as Damping
from ._solver._search import NielsenDamping as NielsenDamping
from ._solver.optimistix import _Held as OptimistixHeld  # noqa: F401
from ._solver.optimistix import _loss as optimistix_loss  # noqa: F401
from ._solver.optimistix import _residuals as optimistix_residuals  # noqa: F401
from ._solver_arg import as_solvers as as_solvers
from ._starts import theta_starts as theta_starts
from ._strategy import MATRIX_FREE_MIN_THETA as MATRIX_FREE_MIN_THETA
from ._strategy import PARALLEL_MIN_T as PARALLEL_MIN_T
from ._strategy import is_parallel as is_parallel
from ._strategy import least_squares_solver as least_squares_solver
from ._strategy import sensitivity_strategy as sensitivity_strategy
from .datasets._download import SOURCES as DATASET_SOURCES  # noqa: F401
from .datasets._download import sha256 as sha256
from .datasets._locations import data_hidden as data_hidden
from .sparsity import _is_float as is_float_leaf  # noqa: F401

# isort: split
# Modules whose globals a test replaces with `monkeypatch.setattr`: `COVARIANCE_MAX_THETA`
# of `assemble_module`, `STARTS_IN_TURN` of `iterate_module`, `CPU_OPTIONS` of
# `jit_module`, `TRIAL_COLUMNS` of `least_squares_module`, `loss_impl` of
# `simulate_module`, `newton_rollout` of `strategy_module`, `__file__` of
# `locations_module`.
from . import _assemble as assemble_module  # noqa: F401
from . import _iterate as iterate_module  # noqa: F401
from . import _jit as jit_module  # noqa: F401
from . import _simulate as simulate_module  # noqa: F401
from . import _strategy as strategy_module  # noqa: F401
from ._solver import least_squares as least_squares_module  # noqa: F401
from .datasets import _locations as locations_module  # noqa: F401
