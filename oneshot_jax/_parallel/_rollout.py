r"""The rollout of eq. (7) by Newton iterations over the whole record (DEER), safeguarded.

The states x_1..x_L of x_{k+1} = f(x_k, u_k, theta) (eq. 7) are the root of the residual
F(x)_k = x_{k+1} - f(x_k, u_k, theta), k = 0..L-1. DEER (Lim et al., ICLR 2024) solves
F(x) = 0 by Newton's method: about the current iterate xbar, the increment d = x - xbar
solves the linear recurrence

    d_0 = 0,   d_{k+1} = A_k d_k + r_k,   A_k = f_x(xbar_k, u_k, theta),
    r_k = f(xbar_k, u_k, theta) - xbar_{k+1},

one associative scan (`linear_recurrence`) of depth O(log L). Every Jacobian and residual
is evaluated at all k at once (vmapped forward mode), so an iteration is a few large
parallel operations instead of L small sequential ones. Writing the step for the
increment rather than for x keeps the scan's roundoff relative to the (small) increment.

The safeguards, in order:

1. **Newton (DEER).** From the constant guess x_k = x_0, at most `max_iter` iterations.
   Converged when max|d| <= rtol (max|x| + tiny) (the max over the whole chunk,
   rtol = 256 eps of the state's dtype by default); the converged increment is applied,
   so the error left is O(|d|^2), at roundoff. A Newton step also measures conditioning:
   near the solution d is the residual's roundoff amplified by the products of the A_k,
   so a trajectory too sensitive to be reproduced to rtol does not pass the test (within
   a chunk: with `chunk_size`, a chunk's test does not see how the later chunks amplify
   the state it hands on, and a chaotic record can drift from the sequential one). Newton
   gives up on a non-finite iterate (it diverges on unstable and chaotic dynamics), at
   the iteration cap, or after 5 iterations without a new smallest ||r||^2.
2. **Damped (ELK).** Levenberg-Marquardt steps (`_elk.py`: ELK, Gonzalez et al.,
   NeurIPS 2024) from the Newton iterate with the smallest ||r||^2, at most `max_iter`:
   a step that lowers ||r||^2 is accepted and the damping divided by 3, otherwise the
   damping is multiplied by 3 (starting from `damping`). The Jacobian of the residual
   F is unit lower block-bidiagonal, hence never singular, so every stationary point of
   ||F||^2 is the trajectory; in floating point a long unstable stretch can still stall
   it. The phase ends when a step is negligible (by the same test); one undamped Newton
   step must then pass the test too, so the damped solution is held to Newton's standard.
3. **Sequential fallback.** Otherwise the chunk is rolled out by the sequential loop
   x_{k+1} = f(x_k, u_k, theta), the definition of eq. (7): the result is never a
   non-converged iterate. Under `vmap` the loop's trip count is 0 for the trajectories
   that converged, and L while any of the batch needs it.

`jacobian="diagonal"` replaces A_k by its diagonal in both iterations (quasi-DEER and
quasi-ELK): O(L n) memory instead of O(L n^2) and elementwise scans, at the price of
linear instead of quadratic convergence: the error left after the last increment passes
the test is about rtol q / (1 - q) of max|x|, q the iteration's contraction factor, rather
than roundoff.

Memory: with `chunk_size = c` the record is solved c steps at a time (a parallel solve
inside a chunk, the last state carried sequentially to the next; the last chunk is padded
with steps that hold the state), so the iterations need O(c n^2) (`"full"`; O(c n) for
`"diagonal"`) plus O(L n) for the states themselves, against O(L n^2) unchunked. The
constant is large: the loop keeps the iterate, the best iterate, a linearisation and the
damped stage's filter elements. At n = 4 in float64, XLA's memory analysis
(`benchmarks/parallel.py --memory`) gives 3.0 GiB for L = 1e6 unchunked (about 3.2 kB a
step, 25 times the stacked Jacobians), 0.35 GiB with `chunk_size = 1e5`, and 1.0 GiB for
L = 1e7 with `chunk_size = 1e5` (0.3 GiB of it the states). The number of sequential
steps is L / c, each a whole parallel solve.

Differentiation: the states are defined implicitly by F(x, theta) = 0, and their tangent
solves the sensitivity recursion dx_{k+1} = A_k dx_k + f_theta dtheta + f_u du_k,
dx_0 = dx0 (a `custom_jvp`, evaluated by the same associative scan), so `jax.jvp`,
`jax.grad` and `jax.jacfwd` of the rollout never differentiate the iterations.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._chunks import chunked_scan
from ._elk import diagonal_elk_increment, elk_increment
from ._recurrence import diagonal_linear_recurrence, linear_recurrence

NEWTON, DAMPED, SEQUENTIAL = 0, 1, 2
"""Codes of `RolloutInfo.method`: which solve produced the states."""
METHOD_NAMES = ("newton", "damped", "sequential")
# Newton stops after this many iterations without a new smallest residual.
_PATIENCE = 5
# The Levenberg-Marquardt damping is divided by this on an accepted step, else multiplied.
_DAMPING_FACTOR = 3.0


class RolloutInfo(NamedTuple):
    """How `newton_rollout` obtained the states (arrays; with a leading axis under vmap).

    - `method`: int, the last-resort solve taken in any chunk: `NEWTON` (0, DEER),
      `DAMPED` (1, ELK then a Newton step) or `SEQUENTIAL` (2, the sequential loop).
    - `converged`: bool, whether the parallel iterations converged in every chunk. With
      `fallback=False` the states of a chunk that did not converge are its best iterate
      (smallest residual), not a trajectory of the model: check this flag.
    - `fallback`: bool, whether the sequential fallback ran (in any chunk).
    - `newton_iterations`, `damped_iterations`: ints, iterations summed over chunks.
    - `chunks`: int, the number of chunks.
    """

    method: jax.Array
    converged: jax.Array
    fallback: jax.Array
    newton_iterations: jax.Array
    damped_iterations: jax.Array
    chunks: jax.Array


class NewtonOptions(NamedTuple):
    """Options of the parallel rollout (hashable: a static argument under jit)."""

    rtol: float | None = None
    max_iter: int = 50
    damping: float = 1.0
    jacobian: str = "full"
    fallback: bool = True
    chunk_size: int | None = None


def check_options(options):
    """Validate `NewtonOptions`, with errors that name the option."""
    if options.rtol is not None and not (0 < options.rtol < 1):
        raise ValueError(f"`rtol` must be in (0, 1) or None, got {options.rtol!r}.")
    if int(options.max_iter) != options.max_iter or options.max_iter < 1:
        raise ValueError(f"`max_iter` must be an integer >= 1, got {options.max_iter!r}.")
    if not (options.damping > 0 and np.isfinite(options.damping)):
        raise ValueError(f"`damping` must be a finite positive number, got {options.damping!r}.")
    if options.jacobian not in ("full", "diagonal"):
        raise ValueError(f"`jacobian` must be 'full' or 'diagonal', got {options.jacobian!r}.")
    if options.chunk_size is not None and (
        int(options.chunk_size) != options.chunk_size or options.chunk_size < 1
    ):
        raise ValueError(
            f"`chunk_size` must be an integer >= 1 or None, got {options.chunk_size!r}."
        )
    return options


def default_rtol(dtype):
    """256 eps of `dtype`: the default convergence tolerance of the Newton iterations."""
    return 256 * float(jnp.finfo(dtype).eps)


def step_jacobians(step, theta, xs, us, diagonal):
    """f_x(xs[k], us[k], theta) for all k: (L, n, n), or its diagonal (L, n).

    Forward mode, vmapped over k. The diagonal takes one JVP per state component (each
    keeping only its own entry) in a `lax.map`, so that its memory stays O(L n).
    """
    n = xs.shape[-1]
    if not diagonal:
        return jax.vmap(jax.jacfwd(step), in_axes=(0, 0, None))(xs, us, theta)
    if n <= 16:
        J = jax.vmap(jax.jacfwd(step), in_axes=(0, 0, None))(xs, us, theta)
        return jnp.diagonal(J, axis1=-2, axis2=-1)

    def column(i):
        e = jnp.zeros((n,), xs.dtype).at[i].set(1.0)
        jvp = lambda x, u: jax.jvp(lambda x: step(x, u, theta), (x,), (e,))[1][i]  # noqa: E731
        return jax.vmap(jvp)(xs, us)

    return jax.lax.map(column, jnp.arange(n)).T


def _sequential(step, theta, x0, us, n_steps):
    """x_1..x_L of eq. (7) by the sequential loop, running only the first `n_steps` steps
    (0 or L): a while loop, so that under vmap it costs nothing unless some trajectory
    needs it (a `lax.cond` would run both branches)."""
    L = jax.tree_util.tree_leaves(us)[0].shape[0]

    def body(carry):
        k, x, out = carry
        x = step(x, jax.tree_util.tree_map(lambda a: a[k], us), theta)
        return k + 1, x, jax.lax.dynamic_update_index_in_dim(out, x, k, 0)

    out = jnp.zeros((L, x0.shape[0]), x0.dtype)
    return jax.lax.while_loop(lambda c: c[0] < n_steps, body, (0, x0, out))[2]


def _once_if(pred, fn, default):
    """`fn()` if `pred` else `default`, as a while loop of 0 or 1 trips: under `vmap` it
    runs if some element needs it (a `lax.cond` there would always run both branches)."""
    body = lambda c: (jnp.array(False), fn())  # noqa: E731
    return jax.lax.while_loop(lambda c: c[0], body, (pred, default))[1]


_RUNNING, _CONVERGED, _FAILED = 0, 1, 2


def _status(converged, failed):
    return jnp.where(converged, _CONVERGED, jnp.where(failed, _FAILED, _RUNNING)).astype(jnp.int32)


class _Newton(NamedTuple):
    x: jax.Array  # (L, n): the iterate x_1..x_L
    A: jax.Array  # its linearisation: Jacobians (L, n, n) or their diagonals (L, n)
    r: jax.Array  # and residuals f(x_k) - x_{k+1} (L, n)
    best_x: jax.Array  # the iterate with the smallest ||r||^2
    best_merit: jax.Array
    since_best: jax.Array  # iterations since best_merit last improved
    passes: jax.Array  # the first pass only linearises the initial guess
    status: jax.Array


class _Damped(NamedTuple):
    x: jax.Array  # the last accepted iterate
    A: jax.Array
    r: jax.Array
    merit: jax.Array  # its ||r||^2
    damping: jax.Array  # Levenberg-Marquardt lambda
    passes: jax.Array
    status: jax.Array  # converged here: the last step was negligible


def _solve_chunk(step, theta, x0, us, options):
    """States x_1..x_L of x_{k+1} = step(x_k, us[k]) and this chunk's info (`us`: a pytree
    with leading axis L).

    Two `while_loop`s (Newton; Levenberg-Marquardt, which runs 0 times when Newton
    converged, and under `vmap` only while some trajectory needs it), a Newton polish and
    the sequential fallback. A pass of either loop takes a step from the current
    linearisation and linearises the new iterate; the first pass, with a zero
    linearisation, takes no step.
    """
    L, n = jax.tree_util.tree_leaves(us)[0].shape[0], x0.shape[0]
    dtype = x0.dtype
    diagonal = options.jacobian == "diagonal"
    rtol = default_rtol(dtype) if options.rtol is None else options.rtol
    tiny = jnp.finfo(dtype).tiny
    f = jax.vmap(step, in_axes=(0, 0, None))

    def linearise(x):
        x_prev = jnp.concatenate([x0[None], x[:-1]])
        r = f(x_prev, us, theta) - x
        return step_jacobians(step, theta, x_prev, us, diagonal), r

    def newton(A, r):
        zero = jnp.zeros((n,), dtype)
        return diagonal_linear_recurrence(A, r, zero) if diagonal else linear_recurrence(A, r, zero)

    def damped(A, r, damping):
        return diagonal_elk_increment(A, r, damping) if diagonal else elk_increment(A, r, damping)

    def small(d, x):
        return jnp.all(jnp.isfinite(x)) & (
            jnp.max(jnp.abs(d)) <= rtol * (jnp.max(jnp.abs(x)) + tiny)
        )

    zero_A = jnp.zeros((L, n) if diagonal else (L, n, n), dtype)
    zero_r = jnp.zeros((L, n), dtype)
    inf = jnp.asarray(jnp.inf, dtype)
    zero_i = jnp.int32(0)

    # 1. Newton (DEER) from the constant guess.
    def newton_body(s):
        first = s.passes == 0
        d = newton(s.A, s.r)  # zero on the first pass (zero linearisation)
        x_try = s.x + d
        converged = ~first & small(d, x_try)
        # A converged iterate needs no linearisation.
        A, r = jax.lax.cond(converged, lambda: (s.A, s.r), lambda: linearise(x_try))
        merit = jnp.sum(r * r)
        better = merit < s.best_merit  # NaN compares False
        since_best = jnp.where(better, 0, s.since_best + 1).astype(jnp.int32)
        passes = s.passes + 1
        failed = ~jnp.isfinite(merit) | (passes > options.max_iter) | (since_best >= _PATIENCE)
        return _Newton(
            x=x_try,
            A=A,
            r=r,
            best_x=jnp.where(better, x_try, s.best_x),
            best_merit=jnp.where(better, merit, s.best_merit),
            since_best=since_best,
            passes=passes,
            status=_status(converged, failed),
        )

    guess = jnp.broadcast_to(x0, (L, n))
    s1 = jax.lax.while_loop(
        lambda s: s.status == _RUNNING,
        newton_body,
        _Newton(guess, zero_A, zero_r, guess, inf, zero_i, zero_i, jnp.int32(_RUNNING)),
    )
    newton_ok = s1.status == _CONVERGED

    # 2. Levenberg-Marquardt (ELK) from the best Newton iterate: a step is accepted if it
    # lowers ||r||^2 (and the damping shrinks), else the damping grows. A solution and a
    # stall both end in a negligible step; a Newton step then decides.
    def damped_body(s):
        first = s.passes == 0
        d = jax.lax.cond(first, lambda: zero_r, lambda: damped(s.A, s.r, s.damping))
        x_try = s.x + d
        A, r = linearise(x_try)
        merit = jnp.sum(r * r)
        accept = merit < s.merit  # always on the first pass, unless non-finite
        passes = s.passes + 1
        stop = ~first & small(d, x_try)
        failed = (first & ~accept) | (passes > options.max_iter)
        pick = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        factor = jnp.where(accept, 1.0 / _DAMPING_FACTOR, _DAMPING_FACTOR)
        return _Damped(
            x=pick(x_try, s.x),
            A=pick(A, s.A),
            r=pick(r, s.r),
            merit=pick(merit, s.merit),
            damping=jnp.where(first, s.damping, s.damping * factor),
            passes=passes,
            status=_status(stop, failed),
        )

    s2 = jax.lax.while_loop(
        lambda s: s.status == _RUNNING,
        damped_body,
        _Damped(
            s1.best_x,
            zero_A,
            zero_r,
            inf,
            jnp.asarray(options.damping, dtype),
            zero_i,
            jnp.where(newton_ok, _CONVERGED, _RUNNING).astype(jnp.int32),
        ),
    )

    # Hold the damped solution to Newton's standard: one undamped step that must pass too.
    def polish():
        d = newton(s2.A, s2.r)
        return s2.x + d, small(d, s2.x + d)

    tried = ~newton_ok & (s2.status == _CONVERGED)
    polished, polish_ok = _once_if(tried, polish, (s2.x, jnp.array(False)))
    damped_ok = tried & polish_ok
    converged = newton_ok | damped_ok
    x = jnp.where(newton_ok, s1.x, jnp.where(damped_ok, polished, s2.x))
    fallback = ~converged & options.fallback
    x = jnp.where(fallback, _sequential(step, theta, x0, us, jnp.where(fallback, L, 0)), x)
    damped_it = jnp.maximum(s2.passes - 1, 0)
    method = jnp.where(fallback, SEQUENTIAL, jnp.where(newton_ok, NEWTON, DAMPED))
    info = RolloutInfo(
        method=method.astype(jnp.int32),
        converged=converged,
        fallback=fallback,
        newton_iterations=s1.passes - 1,
        damped_iterations=damped_it.astype(jnp.int32),
        chunks=jnp.int32(1),
    )
    return x, info


def _merge(info):
    """One `RolloutInfo` from per-chunk rows."""
    return RolloutInfo(
        method=jnp.max(info.method).astype(jnp.int32),
        converged=jnp.all(info.converged),
        fallback=jnp.any(info.fallback),
        newton_iterations=jnp.sum(info.newton_iterations).astype(jnp.int32),
        damped_iterations=jnp.sum(info.damped_iterations).astype(jnp.int32),
        chunks=jnp.sum(info.chunks).astype(jnp.int32),
    )


def _holding(step):
    """The step on inputs (u, valid): a padding step (valid False) holds the state."""
    return lambda x, u, theta: jnp.where(u[1], step(x, u[0], theta), x)


def _states(step, options, theta, x0, us):
    """x_1..x_L for the steps us (L, n_u) and the merged info, chunk by chunk."""
    L = us.shape[0]
    if L == 0:
        info = RolloutInfo(
            jnp.int32(NEWTON),
            jnp.array(True),
            jnp.array(False),
            jnp.int32(0),
            jnp.int32(0),
            jnp.int32(0),
        )
        return jnp.zeros((0, x0.shape[0]), x0.dtype), info

    def fn(x_start, chunk):
        xs, info = _solve_chunk(_holding(step), theta, x_start, chunk, options)
        return xs[-1], (xs, info)

    _, xs, info = chunked_scan(fn, x0, us, options.chunk_size)
    return xs, _merge(info)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _states_diff(step, options, theta, x0, us):
    return _states(step, options, theta, x0, us)


@_states_diff.defjvp
def _states_jvp(step, options, primals, tangents):
    """Tangent of the implicitly defined states: dx_{k+1} = A_k dx_k + f_theta dtheta +
    f_u du_k, dx_0 = dx0, by the associative scan (chunked like the primal)."""
    theta, x0, us = primals
    dtheta, dx0, dus = tangents
    xs, info = _states(step, options, theta, x0, us)
    x_prev = jnp.concatenate([x0[None], xs[:-1]])

    def fn(dx_start, chunk):
        (x_c, u_c, du_c), valid = chunk
        A = step_jacobians(_holding(step), theta, x_c, (u_c, valid), diagonal=False)

        def drive(x, u, du, v):
            push = jax.jvp(lambda th, u: step(x, u, th), (theta, u), (dtheta, du))[1]
            return jnp.where(v, push, 0.0)

        dxs = linear_recurrence(A, jax.vmap(drive)(x_c, u_c, du_c, valid), dx_start)
        return dxs[-1], (dxs, ())

    if us.shape[0] == 0:
        dxs = jnp.zeros_like(xs)
    else:
        _, dxs, _ = chunked_scan(fn, dx0, (x_prev, us, dus), options.chunk_size)
    zeros = jax.tree_util.tree_map(lambda a: np.zeros(a.shape, dtype=jax.dtypes.float0), info)
    return (xs, info), (dxs, zeros)


def newton_rollout(
    step,
    theta,
    x0,
    us,
    *,
    rtol=None,
    max_iter=50,
    damping=1.0,
    jacobian="full",
    fallback=True,
    chunk_size=None,
):
    """States x_0..x_{T-1} of eq. (7), x_{k+1} = step(x_k, us[k], theta), in parallel.

    The same states as `oneshot_jax._simulate.rollout` (the last input is not used), by
    DEER Newton iterations with a damped (ELK) stage and a sequential fallback; see this
    module's docstring for the algorithm, its convergence test and its memory cost.

    **Arguments:**

    - `step`: `step(x, u, theta) -> x_next` (a `Model.step`).
    - `theta`: parameter pytree.
    - `x0`: (n,) initial state. `us`: (T, n_u) inputs.
    - `rtol`: convergence tolerance on max|increment| / max|x| (default 256 eps).
    - `max_iter`: iteration cap of the Newton stage and of the damped stage, each.
    - `damping`: ELK's lambda = 1 / sigma^2 (larger: shorter, safer steps).
    - `jacobian`: `"full"` (DEER / ELK) or `"diagonal"` (quasi-DEER / quasi-ELK).
    - `fallback`: roll out sequentially where the parallel iterations do not converge
        (default). With False, such a chunk holds its best iterate and
        `info.converged` is False.
    - `chunk_size`: steps per parallel solve (None: the whole record at once).

    **Returns:**

    `(xs, info)`: `xs` of shape (T, n) with `xs[0] = x0`, and a `RolloutInfo`.
    Differentiable (`jax.jvp`, `jax.grad`) through the implicit function theorem.
    """
    options = check_options(
        NewtonOptions(rtol, int(max_iter), float(damping), jacobian, bool(fallback), chunk_size)
    )
    x0 = jnp.asarray(x0)
    us = jnp.asarray(us)
    if x0.ndim != 1:
        raise ValueError(f"`x0` must have shape (n,), got shape {x0.shape}.")
    if us.ndim < 2 or us.shape[0] < 1:
        raise ValueError(
            f"`us` must have shape (T, n_u) (or (T, 2, n_u) for a first-order hold) with "
            f"T >= 1, got shape {us.shape}."
        )
    if not jnp.issubdtype(x0.dtype, jnp.floating):
        raise ValueError(f"`x0` must be a floating array, got dtype {x0.dtype}.")
    xs, info = _states_diff(step, options, theta, x0, us[:-1])
    return jnp.concatenate([x0[None], xs]), info
