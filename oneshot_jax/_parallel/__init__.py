"""Parallel-in-time evaluation of the rollout, the one-shot gradient and the sensitivities.

DEER (Lim et al., ICLR 2024): Newton iterations over the whole record, each a linear
recurrence solved by a parallel prefix scan in O(log T) depth (`_recurrence.py`); ELK and
quasi-DEER (Gonzalez et al., NeurIPS 2024): a damped Levenberg-Marquardt stage by a
parallel Kalman smoother (`_elk.py`) and diagonal Jacobians; a sequential fallback where
neither converges (`_rollout.py`). The one-shot gradient and the sensitivities replace
their recursions over k by the same scans (`_adjoint.py`); long records go chunk by chunk
(`_chunks.py`).
"""

from ._adjoint import parallel_sensitivities as parallel_sensitivities
from ._adjoint import parallel_value_and_grad as parallel_value_and_grad
from ._adjoint import rollout as rollout
from ._adjoint import sensitivities_of_states as sensitivities_of_states
from ._adjoint import value_and_grad_of_states as value_and_grad_of_states
from ._recurrence import diagonal_linear_recurrence as diagonal_linear_recurrence
from ._recurrence import linear_recurrence as linear_recurrence
from ._recurrence import matrix_linear_recurrence as matrix_linear_recurrence
from ._recurrence import reverse_diagonal_linear_recurrence as reverse_diagonal_linear_recurrence
from ._recurrence import reverse_linear_recurrence as reverse_linear_recurrence
from ._report import report as report
from ._rollout import METHOD_NAMES as METHOD_NAMES
from ._rollout import NewtonOptions as NewtonOptions
from ._rollout import RolloutInfo as RolloutInfo
from ._rollout import newton_rollout as newton_rollout
