r"""Strategies: how the rollout (eq. 7), the one-shot gradient's reverse recursion
(eq. 17, 20) and the forward sensitivities are evaluated, and the one home of the "auto"
rule (and of the least-squares solvers' choice of normal-equation solve).

A strategy is an object (`AbstractStrategy`) whose methods run the rollout
(`rollout` / `states`), the reverse sweep (`reverse_sweep`: Gamma_k in, lam_0 and the theta
term out) and the forward sensitivities (`sensitivities`, `tangents`); the recursions
themselves are written once, in `oneshot_jax._kernels`, and a strategy only says how a
step is applied and how the recursion runs:

- `Jacobian()` (`"jacobian"`): every J^{x/x}_k (and, for few parameters, J^{x/theta}_k) is
  formed at once after the forward pass by vmapped forward-mode JVPs (the paper's
  Remark 1); the recursions are then small matrix products. Best for small states.
- `VJP()` (`"vjp"`, matrix-free): the recursions push vectors through the step as VJPs
  (gradient) or JVPs (sensitivities) inside the scan and never form J^{x/x}; memory
  O(T n_x). Best for large or sparse states and large batches.
- `ParallelInTime(...)` (`"parallel"`): parallel in time (`oneshot_jax._parallel`): the
  rollout by Newton iterations whose linear recurrences are associative scans (DEER, with
  a damped stage and a sequential fallback), and the gradient's and the sensitivities'
  recursions as associative scans. O(log T) depth instead of T sequential steps: for
  accelerators, where a sequential scan pays a kernel launch per step. On a CPU the
  sequential strategies are faster (`benchmarks/parallel.py`).
- `Auto()` (`"auto"`): resolves to one of the above (`Auto.resolve`).

Whatever the strategy, the gradient's theta term for a theta larger than
`THETA_FORWARD_MIN` (or n_x) is one reverse-mode VJP of the vmapped step after the scan
(`_kernels.theta_term_vjp`): the gradient costs a fixed number of model evaluations per
step, whatever n_theta (`benchmarks/hybrid.py` measures it).

The least-squares solvers (`GaussNewton`, `LevenbergMarquardt`) form the residual
Jacobian with one forward-sensitivity column per free parameter, which grows with
n_theta in time (n_theta JVPs per step) and memory (R n_theta, plus n_theta^2 for
J^T J). Their `linear_solver="auto"` (`least_squares_solver`) switches to the
matrix-free normal-equation solve (conjugate gradients on J v and J^T w, see
`_solver/least_squares.py`) above `MATRIX_FREE_MIN_THETA` free entries of theta. For
the same reason `fit` skips the covariance of the estimates above `COVARIANCE_MAX_THETA`.
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ._counts import integral, real
from ._kernels import (
    forward_sweep,
    push,
    reverse_sweep,
    rollout,
    small_product,
    stacked_jacobians,
    stacked_jacobians_T,
    step_jvp,
    step_vjp,
)
from ._parallel import (
    NewtonOptions,
    check_options,
    chunked_scan,
    matrix_linear_recurrence,
    newton_rollout,
    report,
    reverse_linear_recurrence,
)

STRATEGIES = ("auto", "jacobian", "vjp", "parallel")
ACCELERATORS = ("gpu", "tpu", "cuda", "rocm")
# On an accelerator a sequential scan costs one or more kernel launches per step (about
# 10 microseconds), a parallel solve a few dozen launches in all: from a few hundred
# steps on, parallel wins there (on an H100 at T = 512 in every case of
# `benchmarks/parallel.py`, at T = 64 mostly not: `benchmarks/gpu/h100_short.json`).
PARALLEL_MIN_T = 512

LINEAR_SOLVERS = ("auto", "dense", "cg")

# "auto" solves the least-squares normal equations matrix-free (conjugate gradients)
# above this many free entries of theta (`benchmarks/hybrid.py` compares both).
MATRIX_FREE_MIN_THETA = 256
# `fit` computes the covariance of the estimates (a dense Jacobian, one column per free
# parameter, and a p x p eigendecomposition) only up to this many free entries of theta.
COVARIANCE_MAX_THETA = 1024

# The dense residual Jacobian and its forward sensitivities (N T (n_z + n_x) entries per
# column, a column per free variable), which the least-squares solvers' dense solve, the
# first-order test's column norms and the covariance of the estimates form, are formed
# only up to this many bytes: beyond, a long record with many parameters would end the
# whole fit out of memory. Then "auto" solves by conjugate gradients, the column norms are
# estimated (`_optimality.rademacher_diagonal`) and the covariance is not computed.
DENSE_JACOBIAN_BYTES = 2**30


def dense_jacobian_bytes(problem, n_cols: int) -> int:
    """The bytes of `problem`'s dense residual Jacobian and forward sensitivities with
    `n_cols` columns (static shapes)."""
    N, T, n_z = problem.z.shape
    n_x = problem.x0_base.shape[1]
    return int(N) * int(T) * (int(n_z) + int(n_x)) * int(n_cols) * problem.dtype.itemsize


def dense_jacobian_fits(problem, n_cols: int) -> bool:
    """Whether the dense Jacobian of `n_cols` columns stays within `DENSE_JACOBIAN_BYTES`."""
    return dense_jacobian_bytes(problem, n_cols) <= DENSE_JACOBIAN_BYTES


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


def theta_forward_mode(n_theta, n_x, T, itemsize):
    """Whether the `Jacobian()` gradient stacks J^{x/theta}_k too (few parameters, small
    memory); otherwise its theta term is one VJP, whose cost does not grow with n_theta."""
    return n_theta <= max(n_x, THETA_FORWARD_MIN) and T * n_x * n_theta * itemsize <= JACOBIAN_BYTES


def may_run_parallel(strategy) -> bool:
    """Whether a strategy's rollouts may be parallel in time (whose fallbacks the calls
    count and report, `_parallel._report.counting`): `ParallelInTime`, and `Auto` on a GPU
    or TPU (`Auto.resolve` takes it only there). (A function, not a method: an equinox
    module's bound method costs some 25 microseconds a call.)"""
    if isinstance(strategy, ParallelInTime):
        return True
    return isinstance(strategy, Auto) and jax.default_backend() in ACCELERATORS


class AbstractStrategy(eqx.Module):
    """How the rollout of eq. (7), the reverse recursion of the one-shot gradient (eq. 17,
    20) and the forward sensitivities are evaluated. Pass one as `strategy=` to
    `simulate`, `loss`, `value_and_grad` or a solver; the strings `"auto"`, `"jacobian"`,
    `"vjp"` and `"parallel"` are aliases of `Auto()`, `Jacobian()`, `VJP()` and
    `ParallelInTime()`.
    """

    name: ClassVar[str]

    def resolve(self, n_x, T, itemsize, n_traj=1, n_cols=0, sequential=False):
        """The concrete strategy for a problem of this size (see `Auto`): itself.
        `sequential=True` asks for one whose recursions are sequential scans (the
        matrix-free products of the least-squares solvers)."""
        return self

    def rollout(self, model, theta, x0, u):
        """The states x_0..x_{T-1} of eq. (7) for one trajectory and the parallel
        rollout's `RolloutInfo` (None for a sequential one)."""
        return rollout(model, theta, x0, u), None

    def states(self, model, theta, x0, u):
        """The states of `rollout`; a parallel rollout reports whether it fell back to the
        sequential loop (`oneshot_jax._parallel.report`)."""
        xs, info = self.rollout(model, theta, x0, u)
        if info is not None:
            report(info)
        return xs

    @abc.abstractmethod
    def reverse_sweep(self, model, theta, xs, u, Gamma, At=None, theta_forward=True):
        """The reverse recursion of eq. (17) and (20) for one trajectory:
        lam_{T-1} = Gamma_{T-1}, lam_k = Gamma_k + (J^{x/x}_{k+1})^T lam_{k+1}.

        **Arguments:**

        - `model`, `theta`, `u` (T, n_u): the model, its parameters and inputs.
        - `xs`: (T, n_x), the states x_0..x_{T-1}.
        - `Gamma`: (T, n_x), Gamma_k (eq. 14), or any cotangent of the states.
        - `At`: the stacked (J^{x/x}_{k+1})^T of `jacobians_T`, if already formed.
        - `theta_forward`: whether the theta term may be accumulated in forward mode
            (stacked J^{x/theta}_k) for a small theta.

        **Returns:**

        `(lam_0, sum_{k>=1} (J^{x/theta}_k)^T lam_k)`: grad_x0 (eq. 20) and the theta
        term of eq. (17) (a pytree like theta).
        """

    @abc.abstractmethod
    def sensitivities(self, model, theta, f, p, x0, S0, E, u, emit, xs=None):
        """The forward sensitivities S_{k+1} = J^{x/x}_{k+1} S_k + [J^{x/theta}_{k+1}, 0]
        of one trajectory, and what `emit(x_k, u_k, S_k)` makes of them at every k.

        **Arguments:**

        - `model`, `theta`, `x0` (n_x,), `u` (T, n_u): the trajectory.
        - `f`: `f(x, u_step, p)`, the step as a function of the free parameters `p`.
        - `S0`: (n_x, m), dx_0/d(p, x0 free). `E`: (n_p, m), the tangent of p per column.
        - `emit`: `emit(x_k, u_k, S_k)`, the output rows (`_sensitivity.emitter`).
        - `xs`: the states, if already known.

        **Returns:**

        The outputs of `emit` stacked over k = 0..T-1.
        """

    @abc.abstractmethod
    def jacobians_T(self, step, theta, xs, us):
        """What the matrix-free products keep from the linearisation: the stacked
        (J^{x/x}_{k+1})^T (T-1, n_x, n_x), or an empty (0, n_x, n_x) array."""

    @abc.abstractmethod
    def tangents(self, model, theta, xs, u, s0, b, At):
        """s_0..s_{T-1} of s_{k+1} = J^{x/x}_{k+1} s_k + b_k (one forward-sensitivity
        direction), (T, n_x)."""


class Jacobian(AbstractStrategy):
    """Form every per-step Jacobian at once after the forward pass (vmapped forward-mode
    JVPs, the paper's Remark 1); the recursions are small matrix products. For a small
    theta (at most max(n_x, `THETA_FORWARD_MIN`) entries) the gradient's reverse scan also
    accumulates the theta term from the stacked J^{x/theta}_k. Memory O(T n_x^2): best for
    small states."""

    name: ClassVar[str] = "jacobian"

    def reverse_sweep(self, model, theta, xs, u, Gamma, At=None, theta_forward=True):
        step, x_prev, us = model.step, xs[:-1], model.step_inputs(u)
        T, n_x = xs.shape
        # At[j] = (J^{x/x}_{j+1})^T = (d f(x_j, u_j) / d x_j)^T.
        if At is None:
            At = stacked_jacobians_T(step, theta, x_prev, us, "x")
        Bt = None
        n_theta = ravel_pytree(theta)[0].shape[0]
        if theta_forward and theta_forward_mode(n_theta, n_x, T, xs.dtype.itemsize):
            # Bt[j] = (J^{x/theta}_{j+1})^T.
            Bt = stacked_jacobians_T(step, theta, x_prev, us, "theta")
        return reverse_sweep(
            step,
            theta,
            x_prev,
            us,
            Gamma[:-1],
            Gamma[-1],
            steps=At,
            apply_T=small_product,
            theta_rows=Bt,
        )

    def sensitivities(self, model, theta, f, p, x0, S0, E, u, emit, xs=None):
        if xs is None:
            xs = rollout(model, theta, x0, u)
        A, B = stacked_jacobians(f, xs[:-1], model.step_inputs(u), p, S0.shape[1])
        return jax.vmap(emit)(xs, u, forward_sweep(S0, A, small_product, B))

    def jacobians_T(self, step, theta, xs, us):
        return stacked_jacobians_T(step, theta, xs[:-1], us, "x")

    def tangents(self, model, theta, xs, u, s0, b, At):
        return forward_sweep(s0, At, lambda At_k, s: small_product(At_k, s, transpose=True), b)


class VJP(AbstractStrategy):
    """Matrix-free: push vectors through the step as VJPs (gradient) or JVPs
    (sensitivities) inside the scan, never forming J^{x/x} (a banded or sparse step costs
    what its VJP / JVP costs); the sensitivities store only the output rows. Memory
    O(T n_x): best for large or sparse states and large batches."""

    name: ClassVar[str] = "vjp"

    def reverse_sweep(self, model, theta, xs, u, Gamma, At=None, theta_forward=True):
        step, x_prev, us = model.step, xs[:-1], model.step_inputs(u)
        return reverse_sweep(
            step,
            theta,
            x_prev,
            us,
            Gamma[:-1],
            Gamma[-1],
            steps=(x_prev, us),
            apply_T=step_vjp(step, theta),
        )

    def sensitivities(self, model, theta, f, p, x0, S0, E, u, emit, xs=None):
        # Each step emits the outputs of (x_k, S_k), then advances: only the (n_z,
        # columns) rows are stored, never S_k.
        def advance(inp, carry):
            return push(lambda x, q: f(x, inp[0], q), carry[0], p, carry[1], E)

        (x_last, S_last), outs = forward_sweep(
            (x0, S0),
            (model.step_inputs(u), u[:-1]),
            advance,
            emit=lambda inp, carry: emit(carry[0], inp[1], carry[1]),
        )
        last = emit(x_last, u[-1], S_last)
        return jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b[None]], axis=0), outs, last
        )

    def jacobians_T(self, step, theta, xs, us):
        return jnp.zeros((0, xs.shape[1], xs.shape[1]), xs.dtype)

    def tangents(self, model, theta, xs, u, s0, b, At):
        us = model.step_inputs(u)
        return forward_sweep(s0, (xs[:-1], us), step_jvp(model.step, theta), b)


def padded_step_inputs(model, u):
    """What the step sees for every sample k = 0..T-1 (`Model.step_inputs`, T-1 rows), with
    one more row for the step out of x_{T-1}, which is never used."""
    us = model.step_inputs(u)
    last = us[-1:] if us.shape[0] else jnp.zeros((1, *us.shape[1:]), us.dtype)
    return jnp.concatenate([us, last])


class ParallelInTime(AbstractStrategy):
    """Parallel in time: the rollout by DEER Newton iterations whose linear recurrences
    are associative scans, with a damped (ELK) stage and a sequential fallback
    (`oneshot_jax._parallel.newton_rollout`), and the gradient's and the sensitivities'
    recursions as associative scans over the formed Jacobians. O(log T) depth: for
    accelerators (see `docs/guides/parallel.md`).

    **Arguments:**

    - `chunk_size`: steps per parallel solve (None: the whole record at once). The
        rollout, the reverse recursion and the sensitivities then run chunk by chunk,
        carrying the state, lam or S between chunks: memory O(chunk_size n^2) for the
        stacked Jacobians instead of O(T n^2).
    - `jacobian`: `"full"` (DEER / ELK) or `"diagonal"` (quasi-DEER / quasi-ELK: O(T n)
        memory, linear convergence) for the rollout's Newton iterations. The diagonal
        drops the coupling between states: an oscillator (position and velocity driving
        each other) often does not converge with it and falls back to the sequential loop.
    - `max_iter`: iteration cap of the Newton stage and of the damped stage, each.
    - `rtol`: convergence tolerance on max|increment| / max|x| (None: 256 eps).
    - `damping`: ELK's initial Levenberg-Marquardt lambda (larger: shorter, safer steps).
    - `fallback`: roll out sequentially where the parallel iterations do not converge
        (default). With False such a chunk holds its best iterate, whose states (and the
        loss and gradient from them) are not the model's: a RuntimeWarning says so.

    The matrix-free products of the least-squares solvers' conjugate-gradient solve stay
    sequential (`VJP()`).
    """

    name: ClassVar[str] = "parallel"
    chunk_size: int | None = eqx.field(default=None, static=True, converter=integral)
    jacobian: str = eqx.field(default="full", static=True)
    max_iter: int = eqx.field(default=50, static=True, converter=integral)
    rtol: float | None = eqx.field(default=None, static=True, converter=real)
    damping: float = eqx.field(default=1.0, static=True, converter=real)
    fallback: bool = eqx.field(default=True, static=True)

    def __check_init__(self):
        def fail(name, want):
            raise ValueError(
                f"`ParallelInTime(...)`: `{name}` must be {want}, got {getattr(self, name)!r}."
            )

        def integer(value):
            return isinstance(value, (int, np.integer)) and not isinstance(value, bool)

        def number(value):
            return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
                value, bool
            )

        if self.chunk_size is not None and not integer(self.chunk_size):
            fail("chunk_size", "an integer >= 1 or None")
        if not integer(self.max_iter):
            fail("max_iter", "an integer >= 1")
        if self.rtol is not None and not number(self.rtol):
            fail("rtol", "a number in (0, 1) or None")
        if not number(self.damping):
            fail("damping", "a finite positive number")
        if not isinstance(self.fallback, (bool, np.bool_)):
            fail("fallback", "True or False")
        try:
            check_options(self.options())
        except ValueError as err:
            raise ValueError(f"`ParallelInTime(...)`: {err}") from None

    def options(self):
        """The `NewtonOptions` of `newton_rollout`."""
        return NewtonOptions(
            self.rtol, self.max_iter, self.damping, self.jacobian, self.fallback, self.chunk_size
        )

    def resolve(self, n_x, T, itemsize, n_traj=1, n_cols=0, sequential=False):
        return VJP() if sequential else self

    def rollout(self, model, theta, x0, u):
        us = padded_step_inputs(model, u)
        return newton_rollout(model.step, theta, x0, us, **self.options()._asdict())

    def reverse_sweep(self, model, theta, xs, u, Gamma, At=None, theta_forward=True):
        T, n_x = xs.shape
        us = padded_step_inputs(model, u)

        # Step j maps x_j to x_{j+1}: lam_j = Gamma_j + (J^{x/x}_{j+1})^T lam_{j+1}, and
        # lam_{j+1} multiplies J^{x/theta}_{j+1}. Every state gets a step; the one out of
        # x_{T-1} (and any chunk padding) is masked to zero, so that lam_T = 0 gives
        # lam_{T-1} = Gamma_{T-1}.
        def ended(x, u_keep, th):
            u_j, keep = u_keep
            return jnp.where(keep, model.step(x, u_j, th), jnp.zeros_like(x))

        def chunk(carry, inp):
            lam_next, acc = carry
            (x_c, u_c, g_c, has_step), valid = inp
            u_keep = (u_c, has_step & valid)
            At_c = stacked_jacobians_T(ended, theta, x_c, u_keep, "x")
            g_c = jnp.where(valid[:, None], g_c, 0.0)
            lam0, term = reverse_sweep(
                ended,
                theta,
                x_c,
                u_keep,
                g_c,
                lam_next,
                steps=At_c,
                recurrence=reverse_linear_recurrence,
            )
            return (lam0, jax.tree_util.tree_map(jnp.add, acc, term)), ((), ())

        init = (jnp.zeros((n_x,), Gamma.dtype), jax.tree_util.tree_map(jnp.zeros_like, theta))
        has_step = jnp.arange(T) < T - 1
        (lam0, theta_term), _, _ = chunked_scan(
            chunk, init, (xs, us, Gamma, has_step), self.chunk_size, reverse=True
        )
        return lam0, theta_term

    def sensitivities(self, model, theta, f, p, x0, S0, E, u, emit, xs=None):
        if xs is None:
            xs = self.states(model, theta, x0, u)

        # A chunk holds the states x_a..x_b and the steps leaving them; S_a is carried in.
        def chunk(S_first, inp):
            (x_c, us_c, u_c), _ = inp  # rows of the padding are cut off by `chunked_scan`
            A, B = stacked_jacobians(f, x_c, us_c, p, S0.shape[1])
            Ss = forward_sweep(S_first, A, None, B, recurrence=matrix_linear_recurrence)
            return Ss[-1], (jax.vmap(emit)(x_c, u_c, Ss[:-1]), ())

        # The step past the last sample (S_T) is formed and not used, as with `VJP()`.
        _, outs, _ = chunked_scan(chunk, S0, (xs, padded_step_inputs(model, u), u), self.chunk_size)
        return outs

    def jacobians_T(self, step, theta, xs, us):
        return VJP().jacobians_T(step, theta, xs, us)

    def tangents(self, model, theta, xs, u, s0, b, At):
        return VJP().tangents(model, theta, xs, u, s0, b, At)


class Auto(AbstractStrategy):
    """Pick the strategy from the problem's size and the backend (`resolve`):

    - `ParallelInTime()` on a GPU or TPU for records of at least `PARALLEL_MIN_T` = 512
      samples and small states (those `Jacobian()` takes, below: the parallel path stacks
      the per-step Jacobians too, and more; a state of thousands would need gigabytes):
      there a sequential scan costs one or more kernel launches per step (about
      10 microseconds), a parallel solve a few dozen launches in all, so from a few hundred
      steps on parallel wins. On a CPU the sequential scan is faster at every size
      (`benchmarks/parallel.py`), so never there.
    - `VJP()` for the sensitivities of a batch when a step of the scan, over all N
      trajectories, moves more than `JACOBIAN_MAX_BATCH_WORK` = 512 sensitivity entries
      (N n_x n_cols): beyond it the in-scan JVPs are large vectorised operations anyway,
      and forming J^{x/x} costs more (on XLA:CPU with n_x = 2..3 and 5..6 columns the two
      cross between N = 16 and N = 64).
    - Otherwise `Jacobian()` for small states (n_x <= `JACOBIAN_MAX_NX` = 16 and the
      stacked J^{x/x}_k within `JACOBIAN_BYTES` = 256 MiB), `VJP()` for large ones.
    """

    name: ClassVar[str] = "auto"

    def resolve(self, n_x, T, itemsize, n_traj=1, n_cols=0, sequential=False):
        """The concrete strategy for n_x states, T samples of `itemsize` bytes, `n_traj`
        trajectories (vmapped) and `n_cols` sensitivity columns (0 for the gradient);
        `sequential=True` never takes `ParallelInTime()`."""
        # The parallel path stacks the per-step Jacobians too (and more): only for the
        # states `Jacobian()` would take.
        small = n_x <= JACOBIAN_MAX_NX and T * n_x * n_x * itemsize <= JACOBIAN_BYTES
        accelerator = jax.default_backend() in ACCELERATORS
        if not sequential and small and T >= PARALLEL_MIN_T and accelerator:
            return ParallelInTime()
        if n_traj * n_x * n_cols > JACOBIAN_MAX_BATCH_WORK:
            return VJP()
        return Jacobian() if small else VJP()

    def _concrete(self):
        raise TypeError("`Auto()` must be resolved (`Auto.resolve`) before it is used.")

    def reverse_sweep(self, *args, **kwargs):
        self._concrete()

    def sensitivities(self, *args, **kwargs):
        self._concrete()

    def jacobians_T(self, *args, **kwargs):
        self._concrete()

    def tangents(self, *args, **kwargs):
        self._concrete()


_ALIASES = {"auto": Auto, "jacobian": Jacobian, "vjp": VJP, "parallel": ParallelInTime}


def as_strategy(strategy, name="`strategy`") -> AbstractStrategy:
    """The one conversion (and validation) of a `strategy=` argument: a strategy object
    as it is, a string alias ("auto", "jacobian", "vjp", "parallel") as its object.
    Raises a ValueError naming the argument (`name`) for anything else."""
    if isinstance(strategy, AbstractStrategy):
        return strategy
    if isinstance(strategy, str) and strategy in _ALIASES:
        return _ALIASES[strategy]()
    names = ", ".join(repr(s) for s in STRATEGIES[:-1]) + f" or {STRATEGIES[-1]!r}"
    raise ValueError(
        f"{name} must be {names} (or a strategy object: oneshot_jax.Auto(), Jacobian(), "
        f"VJP(), ParallelInTime(...)), got {strategy!r}."
    )


def is_parallel(strategy, T):
    """Whether the time recursions of a record of T samples run in parallel: asked for,
    or "auto" on an accelerator for a long record."""
    return isinstance(as_strategy(strategy).resolve(1, T, 8), ParallelInTime)


def sensitivity_strategy(strategy, n_traj, n_x, n_cols, T, itemsize):
    """The name of the strategy that the sensitivities of N = `n_traj` trajectories
    (vmapped) take (`Auto.resolve`)."""
    return as_strategy(strategy).resolve(n_x, T, itemsize, n_traj, n_cols).name


def least_squares_solver(linear_solver, n_theta, fits=True):
    """Resolve "auto" for the normal equations of `GaussNewton` / `LevenbergMarquardt`:
    the dense structured solve (formed Jacobian) up to `MATRIX_FREE_MIN_THETA` free
    entries of theta, conjugate gradients on Jacobian products above, or where the dense
    Jacobian would not fit (`fits` False: `dense_jacobian_fits`)."""
    if linear_solver != "auto":
        return linear_solver
    return "cg" if n_theta > MATRIX_FREE_MIN_THETA or not fits else "dense"
