"""The one home of the "auto" rule: how per-step Jacobians enter the gradient and the
sensitivities, and how the least-squares solvers solve their normal equations.

- `"jacobian"`: every J^{x/x}_k (and, for few parameters, J^{x/theta}_k) is formed at
  once after the forward pass by vmapped forward-mode JVPs (the paper's Remark 1); the
  recursions are then small matrix products. Best for small states.
- `"vjp"` (matrix-free): the recursions push vectors through the step as VJPs (gradient)
  or JVPs (sensitivities) inside the scan and never form J^{x/x}; memory O(T n_x).
  Best for large or sparse states and large batches.
- `"parallel"`: parallel in time (`oneshot_jax._parallel`): the rollout by Newton
  iterations whose linear recurrences are associative scans (DEER, with a damped stage
  and a sequential fallback), and the gradient's and the sensitivities' recursions as
  associative scans. O(log T) depth instead of T sequential steps: for accelerators, where
  a sequential scan pays a kernel launch per step. On a CPU the sequential strategies are
  faster (`benchmarks/parallel.py`).

"auto" takes "parallel" on a GPU or TPU for records of at least `PARALLEL_MIN_T` samples,
and otherwise "jacobian" for small states and "vjp" for large ones.

Whatever the strategy, the gradient's theta term for a theta larger than
`THETA_FORWARD_MIN` (or n_x) is one reverse-mode VJP of the vmapped step after the scan
(`_gradient.theta_term_vjp`): the gradient costs a fixed number of model evaluations per
step, whatever n_theta (`benchmarks/hybrid.py` measures it).

The least-squares solvers (`GaussNewton`, `LevenbergMarquardt`) form the residual
Jacobian with one forward-sensitivity column per free parameter, which grows with
n_theta in time (n_theta JVPs per step) and memory (R n_theta, plus n_theta^2 for
J^T J). Their `linear_solver="auto"` (`least_squares_solver`) switches to the
matrix-free normal-equation solve (conjugate gradients on J v and J^T w, see
`_solver/least_squares.py`) above `MATRIX_FREE_MIN_THETA` free entries of theta. For
the same reason `fit` skips the covariance of the estimates above `COVARIANCE_MAX_THETA`.
"""

import jax

STRATEGIES = ("auto", "jacobian", "vjp", "parallel")
ACCELERATORS = ("gpu", "tpu", "cuda", "rocm")
# On an accelerator a sequential scan costs one or more kernel launches per step (about
# 10 microseconds), a parallel solve a few dozen launches in all: from a few hundred
# steps on, parallel wins there.
PARALLEL_MIN_T = 512

LINEAR_SOLVERS = ("auto", "dense", "cg")

# "auto" solves the least-squares normal equations matrix-free (conjugate gradients)
# above this many free entries of theta (`benchmarks/hybrid.py` compares both).
MATRIX_FREE_MIN_THETA = 256
# `fit` computes the covariance of the estimates (a dense Jacobian, one column per free
# parameter, and a p x p eigendecomposition) only up to this many free entries of theta.
COVARIANCE_MAX_THETA = 1024

# Above this many bytes for the stacked J^{x/x}_k, "auto" takes the vjp strategy.
JACOBIAN_BYTES = 256 * 2**20
JACOBIAN_MAX_NX = 16
# The "jacobian" gradient also stacks J^{x/theta}_k (forward mode, n_theta JVPs per step)
# when theta is this small; otherwise its theta term is one reverse-mode VJP after the scan.
THETA_FORWARD_MIN = 8
# "auto" forms the per-step Jacobians for the sensitivities only while a step of the scan,
# over all N trajectories, moves at most this many sensitivity entries (N n_x n_cols):
# beyond it the in-scan JVPs are large vectorised operations anyway, and forming J^{x/x}
# costs more (on XLA:CPU with n_x = 2..3 and 5..6 columns the two cross between N = 16
# and N = 64).
JACOBIAN_MAX_BATCH_WORK = 512


def is_parallel(strategy, T):
    """Whether the time recursions run in parallel: asked for, or "auto" on an accelerator
    for a long record."""
    if strategy == "parallel":
        return True
    return strategy == "auto" and T >= PARALLEL_MIN_T and jax.default_backend() in ACCELERATORS


def gradient_strategy(strategy, n_x, T, itemsize):
    """Resolve "auto" for the one-shot gradient of one trajectory: stacked Jacobians for
    small states, in-scan VJPs for large ones."""
    if strategy != "auto":
        return strategy
    small = n_x <= JACOBIAN_MAX_NX and T * n_x * n_x * itemsize <= JACOBIAN_BYTES
    return "jacobian" if small else "vjp"


def theta_forward_mode(n_theta, n_x, T, itemsize):
    """Whether the "jacobian" gradient stacks J^{x/theta}_k too (few parameters, small
    memory); otherwise its theta term is one VJP, whose cost does not grow with n_theta."""
    return n_theta <= max(n_x, THETA_FORWARD_MIN) and T * n_x * n_theta * itemsize <= JACOBIAN_BYTES


def sensitivity_strategy(strategy, n_traj, n_x, n_cols, T, itemsize):
    """Resolve "auto" for the sensitivity recursion of N = `n_traj` trajectories (vmapped):
    formed Jacobians for small states and small batches, where the scan is dominated by its
    per-step cost, matrix-free JVPs otherwise."""
    if strategy != "auto":
        return strategy
    if n_traj * n_x * n_cols > JACOBIAN_MAX_BATCH_WORK:
        return "vjp"
    return gradient_strategy(strategy, n_x, T, itemsize)


def least_squares_solver(linear_solver, n_theta):
    """Resolve "auto" for the normal equations of `GaussNewton` / `LevenbergMarquardt`:
    the dense structured solve (formed Jacobian) up to `MATRIX_FREE_MIN_THETA` free
    entries of theta, conjugate gradients on Jacobian products above."""
    if linear_solver != "auto":
        return linear_solver
    return "cg" if n_theta > MATRIX_FREE_MIN_THETA else "dense"
