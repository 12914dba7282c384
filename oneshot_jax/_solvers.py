"""The optimisation loops behind `fit`: Algorithm 1 (any optax transform) and a
structured Gauss-Newton / Levenberg-Marquardt over the closed-form residual Jacobian.

Both work on a `Problem`: the free parameters as two arrays, `p_theta` (the free entries
of the flattened theta) and `p_x0` (N, m) (the free entries of each trajectory's initial
state). Fixed entries are constants inside `Problem.theta_of` / `Problem.x0_of`, so they
are removed from the variables rather than masked (a masked variable leaves a singular
Jacobian).
"""

import enum
import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

from ._gradient import value_and_grad_impl
from ._sensitivity import sensitivity_strategy, trajectory_jacobian, trajectory_residuals


class StopReason(enum.Enum):
    """Why a fit stopped. `StopReason.X.message` explains it in words."""

    MAX_EPOCHS = 0
    TOL_LOSS = 1
    TOL_GRAD = 2
    CONVERGED = 3
    NO_PROGRESS = 4
    DIVERGED = 5

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    @property
    def success(self) -> bool:
        return self in (StopReason.TOL_LOSS, StopReason.TOL_GRAD, StopReason.CONVERGED)


_MESSAGES = {
    StopReason.MAX_EPOCHS: "reached the maximum number of epochs (E_max) before converging; "
    "raise max_epochs or the learning rates",
    StopReason.TOL_LOSS: "the loss fell below tol_loss (the paper's epsilon)",
    StopReason.TOL_GRAD: "the gradient norm fell below tol_grad (the paper's delta)",
    StopReason.CONVERGED: "converged: the relative step fell below rtol, or the predicted "
    "decrease of the loss fell below machine precision",
    StopReason.NO_PROGRESS: "no step decreased the loss any more (the damping or the line "
    "search gave up) although the model predicted a decrease; check the scaling of the "
    "problem or try another solver or starting point",
    StopReason.DIVERGED: "the simulation diverged (inf or NaN loss); the last finite iterate "
    "is returned",
}
_RUNNING = -1


class Problem(eqx.Module):
    """Data and the parametrisation of the free variables (built by `fit`)."""

    model: eqx.Module
    u: jax.Array  # (N, T, n_u)
    z: jax.Array  # (N, T, n_z)
    weight: jax.Array | None
    sqrt_q: jax.Array | None
    penalty: Callable | None
    penalty_weight: jax.Array
    theta_base: jax.Array  # flat theta with the fixed values
    theta_free: tuple = eqx.field(static=True)  # indices of the free entries (tuple of int)
    unravel: Callable = eqx.field(static=True)
    x0_base: jax.Array  # (N, n_x) with the fixed values (fit passes NumPy arrays here)
    x0_free: tuple = eqx.field(static=True)
    project: Callable | None = eqx.field(static=True)
    lower: jax.Array | None  # bounds on p_theta
    upper: jax.Array | None
    strategy: str = eqx.field(static=True)

    def theta_of(self, p_theta):
        return self.unravel(self.theta_base.at[np.asarray(self.theta_free, int)].set(p_theta))

    def x0_of(self, p_x0):
        return jnp.asarray(self.x0_base).at[:, np.asarray(self.x0_free, int)].set(p_x0)

    def split(self, theta_flat, x0):
        return theta_flat[np.asarray(self.theta_free, int)], x0[:, np.asarray(self.x0_free, int)]

    def feasible(self, p_theta):
        """Project p_theta onto the constraint set (exactly: the result is inside)."""
        if self.lower is not None:
            p_theta = jnp.clip(p_theta, self.lower, self.upper)
        if self.project is not None:
            flat, _ = ravel_pytree(self.project(self.theta_of(p_theta)))
            p_theta = flat[np.asarray(self.theta_free, int)]
            if self.lower is not None:
                p_theta = jnp.clip(p_theta, self.lower, self.upper)
        return p_theta

    def value_and_grad(self, p_theta, p_x0):
        """C and its gradient in the free variables, by the one-shot recursion."""
        C, (g_theta, g_x0) = value_and_grad_impl(
            self.model,
            self.theta_of(p_theta),
            self.x0_of(p_x0),
            self.u,
            self.z,
            self.weight,
            self.penalty,
            self.penalty_weight,
            True,
            self.strategy,
        )
        g_flat, _ = ravel_pytree(g_theta)
        return C, g_flat[np.asarray(self.theta_free, int)], g_x0[:, np.asarray(self.x0_free, int)]

    def _scale(self):
        return 1.0 / jnp.sqrt(jnp.asarray(self.u.shape[0] * self.u.shape[1], self.x0_base.dtype))

    def residuals(self, p_theta, p_x0, penalty=True):
        """Stacked residuals (N, R) with ||r||^2 = C (see `_sensitivity`)."""
        fn = lambda base, p, u, z: trajectory_residuals(  # noqa: E731
            self.model,
            self.theta_of,
            p_theta,
            base.at[np.asarray(self.x0_free, int)].set(p),
            u,
            z,
            self.sqrt_q,
            self.penalty if penalty else None,
            self.penalty_weight,
            self._scale(),
        )
        return jax.vmap(fn)(self.x0_base, p_x0, self.u, self.z)

    def jacobian(self, p_theta, p_x0, penalty=True):
        """Residuals (N, R) and their closed-form Jacobians (N, R, p), (N, R, m)."""
        x0_free = np.asarray(self.x0_free, int)
        N, T = self.u.shape[:2]
        n_x = self.x0_base.shape[1]
        strategy = sensitivity_strategy(
            self.strategy, N, n_x, p_theta.shape[0] + x0_free.size, T, self.x0_base.dtype.itemsize
        )

        def fn(base, p, u, z):
            return trajectory_jacobian(
                self.model,
                self.theta_of,
                p_theta,
                lambda q: base.at[x0_free].set(q),
                p,
                u,
                z,
                self.sqrt_q,
                self.penalty if penalty else None,
                self.penalty_weight,
                self._scale(),
                strategy,
            )

        return jax.vmap(fn)(self.x0_base, p_x0, self.u, self.z)


# ----------------------------------------------------------------------------- Algorithm 1


@functools.lru_cache(maxsize=32)
def adam(lr_theta=1e-3, lr_x0=1e-4, b1=0.9, b2=0.999, eps=1e-8) -> optax.GradientTransformation:
    """Adam with separate learning rates for theta and x0, as in Algorithm 1 (eq. 8-9).

    Acts on the parameter dict `{"theta": ..., "x0": ...}` that `fit` optimises. Calls
    with the same settings return the same object, so `fit` reuses its compiled loop.
    """
    return optax.partition(
        {"theta": optax.adam(lr_theta, b1, b2, eps), "x0": optax.adam(lr_x0, b1, b2, eps)},
        {"theta": "theta", "x0": "x0"},
    )


def _grad_norm(g_theta, g_x0):
    return jnp.sqrt(jnp.sum(g_theta**2) + jnp.sum(g_x0**2))


def run_first_order(problem, optimiser, p_theta, p_x0, max_epochs, tol_loss, tol_grad):
    """Algorithm 1: while l <= E_max and C >= eps and ||grad C|| >= delta: update.

    Any optax transform works; after `optax.apply_updates` theta is projected onto the
    constraint set (Section 3.3), so every iterate is feasible. A non-finite loss or
    gradient stops the loop with `DIVERGED` and returns the last finite iterate.
    """
    dtype = problem.x0_base.dtype
    params = {"theta": p_theta, "x0": p_x0}
    state0 = optimiser.init(params)
    hist = jnp.full((max_epochs + 1, 2 + p_theta.shape[0]), jnp.nan, dtype)

    def cond(carry):
        return carry[4] == _RUNNING

    def body(carry):
        params, opt_state, last, epoch, _, hist, last_C = carry
        C, g_t, g_x = problem.value_and_grad(params["theta"], params["x0"])
        gnorm = _grad_norm(g_t, g_x)
        hist = hist.at[epoch].set(jnp.concatenate([jnp.stack([C, gnorm]), params["theta"]]))
        finite = jnp.isfinite(C) & jnp.isfinite(gnorm)
        code = jnp.select(
            [~finite, C < tol_loss, gnorm < tol_grad, epoch >= max_epochs],
            [
                StopReason.DIVERGED.value,
                StopReason.TOL_LOSS.value,
                StopReason.TOL_GRAD.value,
                StopReason.MAX_EPOCHS.value,
            ],
            _RUNNING,
        )
        # The last finite iterate is this one unless it diverged.
        last = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), params, last)
        last_C = jnp.where(finite, C, last_C)
        updates, new_state = optimiser.update({"theta": g_t, "x0": g_x}, opt_state, params)
        new = optax.apply_updates(params, updates)
        new = {"theta": problem.feasible(new["theta"]), "x0": new["x0"]}
        keep = code != _RUNNING
        params = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), last, new)
        opt_state = jax.tree_util.tree_map(
            lambda a, b: jnp.where(keep, a, b) if eqx.is_array(a) else a, opt_state, new_state
        )
        return params, opt_state, last, epoch + jnp.where(keep, 0, 1), code, hist, last_C

    init = (
        params,
        state0,
        params,
        jnp.array(0),
        jnp.array(_RUNNING),
        hist,
        jnp.array(jnp.inf, dtype),
    )
    params, _, _, epoch, code, hist, C = jax.lax.while_loop(cond, body, init)
    return params["theta"], params["x0"], C, code, epoch, hist, None


# ------------------------------------------------------------ structured least squares


def _normal_blocks(Jt, Jx, r):
    """Blocks of J^T J and J^T r with one block of x0 columns per trajectory (arrow shape)."""
    A = jnp.einsum("nrp,nrq->pq", Jt, Jt)
    B = jnp.einsum("nrp,nrm->npm", Jt, Jx)
    Cb = jnp.einsum("nrm,nrl->nml", Jx, Jx)
    g_t = jnp.einsum("nrp,nr->p", Jt, r)
    g_x = jnp.einsum("nrm,nr->nm", Jx, r)
    return A, B, Cb, g_t, g_x


def _floor(d):
    return jnp.maximum(d, 1e-12 * jnp.maximum(jnp.max(d, initial=0.0), 1e-300))


def _scaled_eigh(M):
    """Eigendecomposition of the Jacobi-scaled D^{-1/2} M D^{-1/2} (unit diagonal) and its
    numerically null eigenvalues. Scaling first makes the cutoff detect collinear
    columns whatever the parameters' units, without dropping small-scale directions."""
    d = jnp.sqrt(jnp.diagonal(M, axis1=-2, axis2=-1))
    d = jnp.where(d > 0, d, 1.0)
    vals, vecs = jnp.linalg.eigh(M / (d[..., :, None] * d[..., None, :]))
    cut = 1e3 * jnp.finfo(M.dtype).eps * jnp.max(jnp.abs(vals), axis=-1, keepdims=True)
    return d, vals, vecs, vals <= cut


def _psd_solve(M, b):
    """M^+ b for symmetric PSD M (batched; b a vector or a matrix per M).

    Gauss-Newton's normal equations are singular when a parameter (or an initial state)
    has no effect at the current point; the pseudo-inverse then gives that direction a
    zero step instead of NaN or a huge one.
    """
    d, vals, vecs, null = _scaled_eigh(M)
    inv = jnp.where(null, 0.0, 1.0 / jnp.where(null, 1.0, vals))
    vector = b.ndim == M.ndim - 1
    b = b[..., None] if vector else b
    coef = jnp.einsum("...ji,...jk->...ik", vecs, b / d[..., None])
    out = jnp.einsum("...ij,...jk->...ik", vecs, inv[..., None] * coef) / d[..., None]
    return out[..., 0] if vector else out


def structured_step(A, B, Cb, g_t, g_x, mu, active):
    """Solve (J^T J + mu D) h = -J^T r by eliminating each trajectory's x0 block.

    With theta columns shared and x0_i columns only in trajectory i, J^T J is an arrow
    matrix [[A, B_1 .. B_N], [B_i^T, C_i]]. The Schur complement
    S = A + mu D_t - sum_i B_i (C_i + mu D_i)^{-1} B_i^T gives h_theta; then
    h_i = -(C_i + mu D_i)^{-1} (g_i + B_i^T h_theta). Cost O(N m^3 + p^3), linear in N.
    D is Marquardt's diag(J^T J), which makes the step invariant to parameter scaling.
    Entries of theta in `active` (at a bound, pushed outwards) are held at zero step.
    """
    m = Cb.shape[-1]
    D_t = _floor(jnp.diag(A))
    if m:
        D_x = jax.vmap(lambda c: _floor(jnp.diag(c)))(Cb)
        Cd = Cb + mu * jax.vmap(jnp.diag)(D_x)
        CinvBt = _psd_solve(Cd, jnp.swapaxes(B, 1, 2))  # (N, m, p)
        Cinvg = _psd_solve(Cd, g_x)  # (N, m)
        S = A + mu * jnp.diag(D_t) - jnp.einsum("npm,nmq->pq", B, CinvBt)
        rhs = g_t - jnp.einsum("npm,nm->p", B, Cinvg)
    else:
        S = A + mu * jnp.diag(D_t)
        rhs = g_t
    act = active.astype(S.dtype)
    keep = 1.0 - act
    S = S * keep[:, None] * keep[None, :] + jnp.diag(act)
    h_t = -_psd_solve(S, rhs * keep) if S.shape[0] else rhs
    if m:
        h_x = -(Cinvg + jnp.einsum("nmp,p->nm", CinvBt, h_t))
    else:
        h_x = jnp.zeros_like(g_x)
    return h_t, h_x


def run_least_squares(problem, method, p_theta, p_x0, max_epochs, tol_loss, tol_grad, rtol):
    """Gauss-Newton (backtracking on the projected arc) or Levenberg-Marquardt (Nielsen's
    damping update) on the closed-form Jacobian, with the structured solve above.

    Box bounds are exact: each iterate is projected (clipped), and bound entries whose
    gradient points outwards are held fixed for the step (an active set), so a bound that
    is active at the optimum neither stalls the other parameters nor is left.
    A non-finite trial loss is a rejected step: LM raises its damping, GN halves its step.
    """
    dtype = problem.x0_base.dtype
    lm = method == "levenberg_marquardt"
    cost = lambda pt, px: jnp.sum(problem.residuals(pt, px) ** 2)  # noqa: E731
    hist = jnp.full((max_epochs + 1, 2 + p_theta.shape[0]), jnp.nan, dtype)

    def linearise(pt, px):
        # Only C and the blocks of J^T J, J^T r are kept: the loop never stores J.
        r, Jt, Jx = problem.jacobian(pt, px)
        return (jnp.sum(r**2), *_normal_blocks(Jt, Jx, r))

    def active_set(pt, g_t):
        if problem.lower is None:
            return jnp.zeros(pt.shape, bool)
        return ((pt <= problem.lower) & (g_t > 0)) | ((pt >= problem.upper) & (g_t < 0))

    def cond(carry):
        return carry[-1] == _RUNNING

    def body(carry):
        pt, px, lin, _, mu, nu, epoch, hist, _ = carry
        C, A, B, Cb, g_t, g_x = lin
        act = active_set(pt, g_t)
        gnorm = 2.0 * _grad_norm(jnp.where(act, 0.0, g_t), g_x)
        hist = hist.at[epoch].set(jnp.concatenate([jnp.stack([C, gnorm]), pt]))
        code = jnp.select(
            [C < tol_loss, gnorm < tol_grad, epoch >= max_epochs],
            [StopReason.TOL_LOSS.value, StopReason.TOL_GRAD.value, StopReason.MAX_EPOCHS.value],
            _RUNNING,
        )
        h_t, h_x = structured_step(A, B, Cb, g_t, g_x, mu, act)

        def trial(alpha):
            nt = problem.feasible(pt + alpha * h_t)
            nx = px + alpha * h_x
            Cn = cost(nt, nx)
            return nt, nx, jnp.where(jnp.isfinite(Cn), Cn, jnp.inf)

        # Decrease of C predicted by the linear model for the full (projected) step.
        nt, nx, Cn = trial(1.0)
        st, sx = nt - pt, nx - px
        # ||J s||^2 from the blocks: s_t A s_t + 2 sum_i s_t B_i s_i + sum_i s_i C_i s_i.
        Js2 = (
            st @ A @ st
            + 2.0 * jnp.einsum("p,npm,nm->", st, B, sx)
            + jnp.einsum("nm,nml,nl->", sx, Cb, sx)
        )
        pred = -(2.0 * (st @ g_t + jnp.sum(sx * g_x)) + Js2)
        # Nothing left to gain at this precision (MINPACK's ftol test at machine epsilon).
        at_precision = pred <= 8 * jnp.finfo(dtype).eps * C
        if lm:
            rho = (C - Cn) / jnp.where(pred > 0, pred, jnp.inf)
            accept = (Cn < C) & (rho > 0)
            mu_new = jnp.where(accept, mu * jnp.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), mu * nu)
            nu_new = jnp.where(accept, 2.0, 2.0 * nu)
            gave_up = mu_new > 1e20
        else:
            # Backtracking: alpha = 1, 1/2, ... until the loss decreases (projected arc).
            def ls_cond(c):
                return (c[1] >= C) & (c[0] > 2.0**-30)

            def ls_body(c):
                alpha = c[0] / 2
                return alpha, trial(alpha)[2]

            alpha, _ = jax.lax.while_loop(ls_cond, ls_body, (jnp.array(1.0, dtype), Cn))
            nt, nx, Cn = jax.lax.cond(alpha < 1, lambda: trial(alpha), lambda: (nt, nx, Cn))
            accept = Cn < C
            mu_new, nu_new = mu, nu
            gave_up = ~accept

        size = jnp.concatenate([jnp.abs(pt), jnp.abs(px).reshape(-1)])
        scale = size + jnp.max(size, initial=1.0)

        def relative(step_t, step_x):
            step = jnp.concatenate([step_t, step_x.reshape(-1)])
            return jnp.max(jnp.abs(step) / scale, initial=0.0)

        small = relative(nt - pt, nx - px) <= rtol
        # A full step at the round-off level of the parameters that cannot decrease C:
        # nothing is left to gain in this precision (matters in float32).
        at_precision = at_precision | (
            ~accept & (relative(h_t, h_x) <= 10 * jnp.sqrt(jnp.finfo(dtype).eps))
        )
        code = jnp.where(
            code != _RUNNING,
            code,
            jnp.select(
                [(accept & small) | at_precision, gave_up],
                [StopReason.CONVERGED.value, StopReason.NO_PROGRESS.value],
                _RUNNING,
            ),
        )
        take = accept & (code == _RUNNING) | (accept & (code == StopReason.CONVERGED.value))
        pt = jnp.where(take, nt, pt)
        px = jnp.where(take, nx, px)
        C_now = jnp.where(take, Cn, C)
        # A converged step is taken without linearising again at its end point: that point
        # is within rtol (relative) of the last linearisation, which the covariance uses.
        relinearise = take & (code == _RUNNING)
        lin = jax.lax.cond(relinearise, lambda: linearise(pt, px), lambda: lin)
        advanced = code == _RUNNING
        epoch = epoch + jnp.where(advanced | take, 1, 0)
        return pt, px, lin, C_now, mu_new, nu_new, epoch, hist, code

    lin0 = linearise(p_theta, p_x0)
    mu0 = jnp.array(1e-3 if lm else 0.0, dtype)
    init = (
        p_theta,
        p_x0,
        lin0,
        lin0[0],
        mu0,
        jnp.array(2.0, dtype),
        jnp.array(0),
        hist,
        jnp.array(_RUNNING),
    )
    pt, px, lin, C, _, _, epoch, hist, code = jax.lax.while_loop(cond, body, init)
    # A non-finite starting loss can never be improved on: report it as diverged.
    code = jnp.where(jnp.isfinite(C), code, StopReason.DIVERGED.value)
    last = jnp.concatenate([jnp.stack([C, jnp.nan]), pt])
    hist = hist.at[epoch].set(jnp.where(jnp.isnan(hist[epoch, 0]), last, hist[epoch]))
    # The last linearisation (at the returned point, or within rtol of it after a
    # converged step) gives the covariance: its blocks are the data residuals' blocks
    # when there is no penalty; the SSE is the returned point's.
    blocks = None if problem.penalty is not None else (C, *lin[1:4])
    return pt, px, C, code, epoch, hist, blocks


def covariance_blocks(problem, p_theta, p_x0, blocks=None):
    """(J^T J)^{-1} blocks of the data residuals at the solution, via the Schur complement:
    the theta block S^{-1} (a pseudo-inverse), the diagonal of each trajectory's x0 block,
    and which parameters are identifiable (outside the null space of S).

    `blocks`: (C, A, B, C_i) of the data residuals at (p_theta, p_x0) when the solver
    already holds them (its last linearisation); otherwise the Jacobian is evaluated here.
    Returns the data SSE ||r||^2 too.
    """
    if blocks is None:
        r, Jt, Jx = problem.jacobian(p_theta, p_x0, penalty=False)
        A, B, Cb, _, _ = _normal_blocks(Jt, Jx, r)
        sse = jnp.sum(r**2)
    else:
        sse, A, B, Cb = blocks
    m = Cb.shape[-1]
    if m:
        Cinv = jnp.linalg.inv(Cb)
        S = A - jnp.einsum("npm,nml,nql->pq", B, Cinv, B)
    else:
        S = A
    # A pseudo-inverse, and a flag per parameter: a parameter with a component in the null
    # space of S does not change the outputs at the solution (not identifiable).
    _, _, vecs, null = _scaled_eigh(S)
    identifiable = ~jnp.any(null[None, :] & (jnp.abs(vecs) > 1e-6), axis=1)
    S_inv = _psd_solve(S, jnp.eye(S.shape[0], dtype=S.dtype))
    if m:
        W = jnp.einsum("nml,npl->nmp", Cinv, B)  # C_i^{-1} B_i^T
        x_diag = jnp.diagonal(Cinv, axis1=1, axis2=2) + jnp.einsum("nmp,pq,nmq->nm", W, S_inv, W)
    else:
        x_diag = jnp.zeros(p_x0.shape, A.dtype)
    return sse, S_inv, x_diag, identifiable
