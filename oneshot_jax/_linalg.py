"""Symmetric positive semi-definite solves shared by the least-squares solvers and the
covariance: the normal equations J^T J of a fit are singular when a parameter or an
initial state has no effect on the outputs, and both then need a pseudo-inverse; the
one elimination of the per-trajectory x0 blocks of the arrow matrix J^T J (`eliminate_x0`);
and the Schur complement of those blocks formed from the Jacobian itself, where it decides
what the data determine (`schur_complement`)."""

from typing import NamedTuple

import jax
import jax.numpy as jnp


def normal_blocks(Jt, Jx, r):
    """Blocks of J^T J and J^T r with one block of x0 columns per trajectory (arrow shape):
    A = sum_i Jt_i^T Jt_i, B_i = Jt_i^T Jx_i, C_i = Jx_i^T Jx_i, g_t = J_t^T r, g_i = Jx_i^T r_i."""
    A = jnp.einsum("nrp,nrq->pq", Jt, Jt)
    B = jnp.einsum("nrp,nrm->npm", Jt, Jx)
    Cb = jnp.einsum("nrm,nrl->nml", Jx, Jx)
    g_t = jnp.einsum("nrp,nr->p", Jt, r)
    g_x = jnp.einsum("nrm,nr->nm", Jx, r)
    return A, B, Cb, g_t, g_x


def schur_complement(Jt, Jx, A):
    """The Schur complement S = A - sum_i B_i C_i^+ B_i^T of the x0 blocks of J^T J (the
    blocks of `normal_blocks`), formed from the Jacobian:

        S = sum_i (P_i J_t,i)^T (P_i J_t,i),   P_i = I - U_i U_i^T,

    U_i an orthonormal basis of the range of trajectory i's x0 columns J_x,i (a QR of the
    Jacobi-scaled J_x,i, then an SVD of its triangular factor), without the directions
    that the cut of `scaled_eigh` deems null in C_i (C_i^+ ignores them too). This is the
    x0-eliminated normal matrix of eq. (17)/(20)'s sensitivities: what the data determine
    of theta once every x0 is fitted. Formed from A, B_i and C_i instead, the subtraction
    cancels: its round-off is about cond(C_i) eps ||A|| (a partly observed oscillator
    whose C_i has a condition number of 1e11 gave an indefinite S and flagged every
    parameter as not identifiable); here it is about eps ||A||. Judge it against diag(A)
    (`identifiable(S, jnp.diag(A))`): a theta column that the x0 columns reproduce leaves
    a remainder of round-off, which its own diagonal would make look regular.

    **Arguments:** `Jt` (N, R, p), `Jx` (N, R, m) and `A` = J_t^T J_t as for
    `normal_blocks` (S is A itself without x0 columns).

    **Returns:** S (p, p).
    """
    if not Jx.shape[-1] or not Jt.shape[-1]:
        return A
    eps = jnp.finfo(Jx.dtype).eps

    def projected(jt, jx):
        d = jnp.sqrt(jnp.sum(jx**2, axis=0))
        q, t = jnp.linalg.qr(jx / jnp.where(d > 0, d, 1.0)[None, :])
        u, s, _ = jnp.linalg.svd(t, full_matrices=False)
        vals = s**2
        U = (q @ u) * (vals > NULL_CUT * eps * jnp.max(vals, initial=0.0))[None, :]
        return jt - U @ (U.T @ jt)

    P = jax.vmap(projected)(Jt, Jx)
    return jnp.einsum("nrp,nrq->pq", P, P)


# The numerical null cut: eigenvalues of a Jacobi-scaled PSD matrix at or below this many
# eps of the largest are round-off (`scaled_eigh`, `schur_complement`).
NULL_CUT = 1e3


def floor(d, rel=1e-12):
    """Diagonal entries floored at `rel` of their largest (Marquardt's scaling D)."""
    return jnp.maximum(d, rel * jnp.maximum(jnp.max(d, initial=0.0), 1e-300))


class Decomposition(NamedTuple):
    """A `scaled_eigh` of a PSD M: M = D^{1/2} V diag(vals) V^T D^{1/2}."""

    d: jax.Array  # D^{1/2}: the scaling's square roots
    vals: jax.Array  # eigenvalues of the scaled matrix
    vecs: jax.Array  # its eigenvectors (columns)
    null: jax.Array  # the eigenvalues at or below 1e3 eps of the largest: numerically null
    cut: jax.Array  # that cutoff (batched as the largest eigenvalue, with a trailing axis)


def scaled_eigh(M, diag=None) -> Decomposition:
    """Eigendecomposition of the Jacobi-scaled D^{-1/2} M D^{-1/2} (unit diagonal) and its
    numerically null eigenvalues. Scaling first makes the cutoff detect collinear
    columns whatever the parameters' units, without dropping small-scale directions.
    `diag`: the D to scale by, where not M's own diagonal (a Schur complement judged
    against the matrix it came from)."""
    d = jnp.sqrt(jnp.diagonal(M, axis1=-2, axis2=-1) if diag is None else diag)
    d = jnp.where(d > 0, d, 1.0)
    vals, vecs = jnp.linalg.eigh(M / (d[..., :, None] * d[..., None, :]))
    top = jnp.max(jnp.abs(vals), axis=-1, keepdims=True, initial=0.0)
    if diag is not None:  # judged against the reference's unit diagonal too
        top = jnp.maximum(top, 1.0)
    cut = NULL_CUT * jnp.finfo(M.dtype).eps * top
    return Decomposition(d, vals, vecs, vals <= cut, cut)


def psd_solve(M, b, diag=None):
    """M^+ b for symmetric PSD M (batched; b a vector or a matrix per M).

    A direction in the null space of M gets a zero step instead of NaN or a huge one.
    `diag`: as for `scaled_eigh`.
    """
    return eigh_solve(scaled_eigh(M, diag), b)


def _reciprocal(vals, null):
    """1 / vals, 0 at the null eigenvalues: the pseudo-inverse's spectrum."""
    return jnp.where(null, 0.0, 1.0 / jnp.where(null, 1.0, vals))


def eigh_solve(decomposition, b, floored=False):
    """`psd_solve` from M's `scaled_eigh` `decomposition`, for a caller that reads the
    decomposition too. `floored`: solve with the null eigenvalues raised to the cutoff
    instead of dropped, (M + the null directions at the cutoff)^{-1} b, so that
    b^T M_c^{-1} b is a lower bound on the decrease the null directions would give
    where the data determine them weakly rather than not at all."""
    d, vals, vecs, null, cut = decomposition
    inv = 1.0 / jnp.maximum(vals, cut) if floored else _reciprocal(vals, null)
    vector = b.ndim == vecs.ndim - 1
    b = b[..., None] if vector else b
    coef = jnp.einsum("...ji,...jk->...ik", vecs, b / d[..., None])
    out = jnp.einsum("...ij,...jk->...ik", vecs, inv[..., None] * coef) / d[..., None]
    return out[..., 0] if vector else out


def numerical_rank(M, diag=None):
    """The numerical rank of a (batched) PSD M: its eigenvalues above the null cutoff of
    `scaled_eigh`, the cutoff of `psd_solve` and of the covariance's identifiability.
    `diag`: as for `scaled_eigh`."""
    return jnp.sum(~scaled_eigh(M, diag).null, axis=-1)


# A variable has a component in a (unit, Jacobi-scaled) null direction above this size:
# not identifiable unless the data determine it as `identified` says (and, for the initial
# states the covariance judges along theta's null directions, without that exception).
NULL_COMPONENT = 1e-6


def identified(decomposition: Decomposition):
    """Per variable of a PSD M, from its `scaled_eigh` `decomposition`: False where the
    outputs do not determine it, i.e. where it has a component in M's numerical null space
    (above `NULL_COMPONENT`) that matters to its variance.

    A variable's variance (scaled) is sum_j v_ij^2 / lambda_j over the eigenpairs; the
    pseudo-inverse keeps the determined directions' part w_i and drops the null ones. The
    variable counts as determined when its null directions, taken with their eigenvalues
    as computed, would add less than w_i (sum_null v_ij^2 / lambda_j < w_i): then the
    pseudo-inverse's standard error is within a factor sqrt(2) of the one that keeps them.
    An exact null direction has an eigenvalue of round-off size (a huge share) or below
    zero (counted as zero): a variable with a component above `NULL_COMPONENT` in it is not
    identifiable (a * b entering as their product; c + 1e-5 a next to them, though c's
    column alone is well determined). This matters where a numerically null direction is
    nearly one variable's and its eigenvalue, though below the cut, is that variable's
    small remaining information: the damping of a hybrid model that a network of the
    velocity reproduces (eigenvalue 9e-14 of the scaled matrix), whose eigenvector carried
    2e-6 of the stiffness and of the input gain, whose variances came from eigenvalues
    near 1e-3 (an added share of about 5 %): those two are determined, their standard
    errors finite.

    In float64 only: in a lower precision the cut (1e3 eps, 1.2e-4 of the largest
    eigenvalue in float32) sets aside directions that carry much of such a variance (the
    same hybrid's stiffness and gain came out 2 to 3 times below their float64 standard
    errors at the same point), and every variable with a null component above
    `NULL_COMPONENT` is not identifiable.
    """
    _, vals, vecs, null, _ = decomposition
    touched = jnp.any(null[..., None, :] & (jnp.abs(vecs) > NULL_COMPONENT), axis=-1)
    if jnp.finfo(vals.dtype).eps > jnp.finfo(jnp.float64).eps:
        return ~touched
    square = vecs**2
    kept = null & (vals > 0)
    share = jnp.where(kept, 1.0 / jnp.where(kept, vals, 1.0), jnp.inf)[..., None, :]
    share = jnp.where(null[..., None, :] & (square > 0), square * share, 0.0)
    determined = jnp.sum(square * _reciprocal(vals, null)[..., None, :], axis=-1)
    return ~(touched & (jnp.sum(share, axis=-1) >= determined))


def identifiable(M, diag=None):
    """Per variable of a PSD M: False where the outputs do not determine it (`identified`).
    `diag`: as for `scaled_eigh`."""
    return identified(scaled_eigh(M, diag))


class Elimination(NamedTuple):
    """The x0 blocks of an arrow matrix [[A, B_1 .. B_N], [B_i^T, C_i]] eliminated, from
    `eliminate_x0`: (C_i)^{-1} applied to B_i^T and to g_i, with C_i damped or not."""

    CinvBt: jax.Array  # (N, m, p): C_i^{-1} B_i^T
    Cinvg: jax.Array  # (N, m): C_i^{-1} g_i
    Cinv: jax.Array | None  # (N, m, m): C_i^+ itself (formed with `pseudo_inverse`)

    def schur(self, A, B):
        """The Schur complement S = A - sum_i B_i C_i^{-1} B_i^T (A given damped or not)."""
        if not B.shape[-1]:
            return A
        if self.Cinv is not None:  # formed: contracted as (B_i C_i^+) B_i^T
            return A - jnp.einsum("npm,nml,nql->pq", B, self.Cinv, B)
        return A - jnp.einsum("npm,nmq->pq", B, self.CinvBt)

    def schur_correction(self, B, v):
        """sum_i B_i C_i^{-1} B_i^T v: what S v subtracts from A v (matrix-free)."""
        return jnp.einsum("npm,nmq,q->p", B, self.CinvBt, v)

    def schur_diagonal(self, B):
        """diag(sum_i B_i C_i^{-1} B_i^T)."""
        return jnp.einsum("npm,nmp->p", B, self.CinvBt)

    def rhs(self, B, g_t):
        """The reduced right-hand side g_t - sum_i B_i C_i^{-1} g_i."""
        if not B.shape[-1]:
            return g_t
        return g_t - jnp.einsum("npm,nm->p", B, self.Cinvg)

    def back(self, h_t):
        """Back-substitution: h_i = -C_i^{-1} (g_i + B_i^T h_theta)."""
        if not self.Cinvg.shape[-1]:
            return jnp.zeros_like(self.Cinvg)
        return -(self.Cinvg + jnp.einsum("nmp,p->nm", self.CinvBt, h_t))

    def covariance(self, S_inv):
        """The x0 blocks of the inverse of the arrow matrix: C_i^+ + W_i S^+ W_i^T with
        W_i = C_i^+ B_i^T (needs `pseudo_inverse`)."""
        if not self.Cinv.shape[-1]:
            return self.Cinv
        W = self.CinvBt
        return self.Cinv + jnp.einsum("nmp,pq,nlq->nml", W, S_inv, W)


def eliminate_x0(B, Cb, g_x=None, mu=None, *, pseudo_inverse=False):
    """Eliminate each trajectory's x0 block of the arrow matrix
    M = [[A, B_1 .. B_N], [B_i^T, C_i]] (J^T J of a fit whose theta columns are shared by
    all trajectories and whose x0_i columns touch trajectory i only, eq. (17)/(20)).

    Solving M h = -(g_t, g_i) reduces to the Schur complement system
    S h_theta = -(g_t - sum_i B_i C_i^{-1} g_i), S = A - sum_i B_i C_i^{-1} B_i^T, and
    h_i = -C_i^{-1} (g_i + B_i^T h_theta) (`Elimination.schur`, `.rhs`, `.back`); the
    inverse of M has the x0 blocks C_i^{-1} + W_i S^{-1} W_i^T, W_i = C_i^{-1} B_i^T
    (`Elimination.covariance`). The cost is O(N m^3) for the x0 blocks, linear in the
    number of trajectories N. This is the one elimination of the package: the damped
    least-squares step (`_solver._linearisation`) and the covariance (`_covariance`).

    **Arguments:**

    - `B`: (N, p, m) the blocks B_i = J_t,i^T J_x,i.
    - `Cb`: (N, m, m) the blocks C_i = J_x,i^T J_x,i.
    - `g_x`: (N, m) the x0 parts g_i = J_x,i^T r_i of the right-hand side (or None).
    - `mu`: Marquardt's damping: C_i + mu D_i with D_i = diag(C_i) floored (`floor`), or
        None for C_i itself.
    - `pseudo_inverse`: form C_i^+ (and W_i = C_i^+ B_i^T from it), for the covariance;
        otherwise C_i^{-1} is applied to B_i^T and g_i by `psd_solve`.

    **Returns:**

    An `Elimination`. Pseudo-inverses throughout: a direction without effect gets a zero
    step (and is flagged as not identifiable by the covariance) instead of NaN.
    """
    m = Cb.shape[-1]
    if not m:
        return Elimination(jnp.swapaxes(B, 1, 2), g_x, Cb if pseudo_inverse else None)
    Cd = Cb
    if mu is not None:
        D_x = jax.vmap(lambda c: floor(jnp.diag(c)))(Cb)
        Cd = Cb + mu * jax.vmap(jnp.diag)(D_x)
    if pseudo_inverse:
        Cinv = psd_solve(Cd, jnp.broadcast_to(jnp.eye(m, dtype=Cd.dtype), Cd.shape))
        CinvBt = jnp.einsum("nml,npl->nmp", Cinv, B)
        Cinvg = None if g_x is None else jnp.einsum("nml,nl->nm", Cinv, g_x)
        return Elimination(CinvBt, Cinvg, Cinv)
    CinvBt = psd_solve(Cd, jnp.swapaxes(B, 1, 2))  # (N, m, p)
    Cinvg = None if g_x is None else psd_solve(Cd, g_x)  # (N, m)
    return Elimination(CinvBt, Cinvg, None)
