"""Symmetric positive semi-definite solves shared by the least-squares solvers and the
covariance: the normal equations J^T J of a fit are singular when a parameter or an
initial state has no effect on the outputs, and both then need a pseudo-inverse."""

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


def floor(d):
    """Diagonal entries floored at 1e-12 of their largest (Marquardt's scaling D)."""
    return jnp.maximum(d, 1e-12 * jnp.maximum(jnp.max(d, initial=0.0), 1e-300))


def scaled_eigh(M):
    """Eigendecomposition of the Jacobi-scaled D^{-1/2} M D^{-1/2} (unit diagonal) and its
    numerically null eigenvalues. Scaling first makes the cutoff detect collinear
    columns whatever the parameters' units, without dropping small-scale directions."""
    d = jnp.sqrt(jnp.diagonal(M, axis1=-2, axis2=-1))
    d = jnp.where(d > 0, d, 1.0)
    vals, vecs = jnp.linalg.eigh(M / (d[..., :, None] * d[..., None, :]))
    top = jnp.max(jnp.abs(vals), axis=-1, keepdims=True, initial=0.0)
    cut = 1e3 * jnp.finfo(M.dtype).eps * top
    return d, vals, vecs, vals <= cut


def psd_solve(M, b):
    """M^+ b for symmetric PSD M (batched; b a vector or a matrix per M).

    A direction in the null space of M gets a zero step instead of NaN or a huge one.
    """
    d, vals, vecs, null = scaled_eigh(M)
    inv = jnp.where(null, 0.0, 1.0 / jnp.where(null, 1.0, vals))
    vector = b.ndim == M.ndim - 1
    b = b[..., None] if vector else b
    coef = jnp.einsum("...ji,...jk->...ik", vecs, b / d[..., None])
    out = jnp.einsum("...ij,...jk->...ik", vecs, inv[..., None] * coef) / d[..., None]
    return out[..., 0] if vector else out


def identifiable(M):
    """Per variable of a PSD M: False where it has a component in M's numerical null
    space (the outputs do not determine it)."""
    _, _, vecs, null = scaled_eigh(M)
    return ~jnp.any(null[..., None, :] & (jnp.abs(vecs) > 1e-6), axis=-1)
