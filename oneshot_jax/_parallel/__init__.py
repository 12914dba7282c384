"""Parallel-in-time scans: the rollout, and the linear recurrences of the one-shot
gradient and of the sensitivities.

DEER (Lim et al., ICLR 2024): Newton iterations over the whole record, each a linear
recurrence solved by a parallel prefix scan in O(log T) depth (`_recurrence.py`); ELK and
quasi-DEER (Gonzalez et al., NeurIPS 2024): a damped Levenberg-Marquardt stage by a
parallel Kalman smoother (`_elk.py`) and diagonal Jacobians; a sequential fallback where
neither converges (`_rollout.py`). Long records go chunk by chunk (`_chunks.py`). The
gradient's recursion (eq. 17, 20) and the sensitivities run on these scans through the
`ParallelInTime` strategy (`oneshot_jax._strategy`, recursions in `oneshot_jax._kernels`);
this package imports neither.
"""

from ._chunks import chunked_scan as chunked_scan
from ._recurrence import diagonal_linear_recurrence as diagonal_linear_recurrence
from ._recurrence import linear_recurrence as linear_recurrence
from ._recurrence import matrix_linear_recurrence as matrix_linear_recurrence
from ._recurrence import reverse_diagonal_linear_recurrence as reverse_diagonal_linear_recurrence
from ._recurrence import reverse_linear_recurrence as reverse_linear_recurrence
from ._report import report as report
from ._rollout import METHOD_NAMES as METHOD_NAMES
from ._rollout import NewtonOptions as NewtonOptions
from ._rollout import RolloutInfo as RolloutInfo
from ._rollout import check_options as check_options
from ._rollout import newton_rollout as newton_rollout
