r"""Linear recurrences in O(log T) depth by `jax.lax.associative_scan`.

Every parallel-in-time routine of this package reduces to one of

    x_{k+1} = A_k x_k + b_k                  (forward: the Newton step of the rollout, eq. 7,
                                              and the sensitivities S_{k+1} = A_k S_k + B_k)
    lam_k   = g_k + At_k lam_{k+1}           (reverse: the multiplier of the one-shot gradient
                                              that replaces the double sums of eq. 17 and 20)

Each step is an affine map e_k = (A_k, b_k): x -> A_k x + b_k. Affine maps compose
associatively, applying e_i and then e_j being

    e_j o e_i = (A_j A_i, A_j b_i + b_j),

so the prefix compositions e_{k} o ... o e_0 = (P_k, c_k), for every k at once, are one
parallel prefix scan (Blelloch 1990), and x_{k+1} = P_k x_0 + c_k. This is the linear solve
at the heart of DEER (Lim et al., "Parallelizing non-linear sequential models over the
sequence length", ICLR 2024) and of quasi-DEER / ELK (Gonzalez et al., "Towards scalable
and stable parallelization of nonlinear RNNs", NeurIPS 2024).

Cost: the scan does O(T) combines in O(log T) depth; a combine costs O(n^3) for full
n x n matrices (O(n^2 m) for an n x m right-hand side) and O(n) for diagonal ones. Memory:
the scan keeps O(T) elements alive, i.e. O(T n^2) for full matrices and O(T n) for
diagonal ones.

Up to T = 512 the compositions are computed by recursive doubling instead (`doubling_scan`:
O(T log T) work, but one compiled combine instead of about 2 log2 T, so a short record
compiles several times faster at the same run time); longer records use
`jax.lax.associative_scan`, whose O(T) work wins there.

Products of small matrices are written as broadcast multiplies and sums (exact IEEE
products and sums in the array's dtype, fused by XLA); larger ones use `einsum` at
`Precision.HIGHEST`, so that a float32 product on a GPU is not silently done in TF32.
"""

import jax
import jax.numpy as jnp
import numpy as np

# Up to this state size, batched matrix products are broadcast multiply-and-sum.
_ELEMENTWISE_MAX_N = 16
# Up to this length the prefix compositions use recursive doubling (`doubling_scan`).
_DOUBLING_MAX_T = 512


def _matmul(A, B):
    """Batched A @ B over leading axes (A (..., n, k), B (..., k, m))."""
    if A.shape[-1] <= _ELEMENTWISE_MAX_N:
        return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)
    return jnp.einsum("...ij,...jk->...ik", A, B, precision=jax.lax.Precision.HIGHEST)


def _matvec(A, b):
    """Batched A @ b over leading axes (A (..., n, k), b (..., k))."""
    if A.shape[-1] <= _ELEMENTWISE_MAX_N:
        return jnp.sum(A * b[..., None, :], axis=-1)
    return jnp.einsum("...ij,...j->...i", A, b, precision=jax.lax.Precision.HIGHEST)


def _apply(A, b):
    """A @ b for a vector (..., n) or a matrix (..., n, m) right-hand side."""
    return _matvec(A, b) if b.ndim == A.ndim - 1 else _matmul(A, b)


def _check(A, b, x0, name_b, name_x0, diagonal):
    if A.ndim != (2 if diagonal else 3):
        want = "(T, n)" if diagonal else "(T, n, n)"
        raise ValueError(f"`A` must have shape {want}, got shape {A.shape}.")
    T, n = A.shape[0], A.shape[1]
    if not diagonal and A.shape[2] != n:
        raise ValueError(f"`A` must hold square matrices (T, n, n), got shape {A.shape}.")
    if b.ndim not in (2, 3) or b.shape[:2] != (T, n) or (diagonal and b.ndim != 2):
        want = f"({T}, {n})" if diagonal else f"({T}, {n}) or ({T}, {n}, m)"
        raise ValueError(f"`{name_b}` must have shape {want} to match `A`, got {b.shape}.")
    if x0.shape != b.shape[1:]:
        raise ValueError(f"`{name_x0}` must have shape {b.shape[1:]}, got shape {x0.shape}.")


def _prefix(compose, elems, reverse=False, diagonal=False):
    """Prefix compositions of the affine maps `elems` = (A, b), by doubling for short records
    and `associative_scan` for long ones (module docstring)."""
    A, b = elems
    if A.shape[0] > _DOUBLING_MAX_T:
        return jax.lax.associative_scan(compose, elems, reverse=reverse)
    eye = jnp.ones(A.shape[1:], A.dtype) if diagonal else jnp.eye(A.shape[-1], dtype=A.dtype)
    return doubling_scan(compose, (eye, jnp.zeros(b.shape[1:], b.dtype)), elems, reverse=reverse)


def _compose(first, second):
    """second o first for (full matrix, vector or matrix offset) affine maps."""
    A1, b1 = first
    A2, b2 = second
    return _matmul(A2, A1), _apply(A2, b1) + b2


def _compose_diagonal(first, second):
    a1, b1 = first
    a2, b2 = second
    return a2 * a1, a2 * b1 + b2


def linear_recurrence(A, b, x0):
    """All states of x_{k+1} = A_k x_k + b_k, k = 0..T-1, by one associative scan.

    The linear solve of a DEER Newton step (Lim et al., ICLR 2024) and, with a matrix
    right-hand side, the sensitivity recursion S_{k+1} = A_k S_k + B_k of
    `oneshot_jax._sensitivity` (see `matrix_linear_recurrence`).

    **Arguments:**

    - `A`: (T, n, n), the transition matrices A_k.
    - `b`: (T, n), or (T, n, m) for m right-hand sides at once (x_k is then n x m).
    - `x0`: (n,), or (n, m): the initial state.

    **Returns:**

    (T, n) (or (T, n, m)): x_1, ..., x_T (x0 itself is not included).

    Depth O(log T), work O(T n^3) (O(T n^2 m) for the offsets), memory O(T n^2).
    """
    _check(A, b, x0, "b", "x0", diagonal=False)
    P, c = _prefix(_compose, (A, b))
    return _apply(P, jnp.broadcast_to(x0, b.shape)) + c


def matrix_linear_recurrence(A, B, S0):
    """S_1..S_T of S_{k+1} = A_k S_k + B_k (S_k is n x m): the sensitivity recursion.

    In `oneshot_jax._sensitivity`, A_k = J^{x/x}_{k+1} and B_k = [J^{x/theta}_{k+1}, 0],
    S_0 = [0, dx0/dp_x0], so that S_k = dx_k / d(theta, x0). Same scan as
    `linear_recurrence` with an n x m offset.

    **Arguments:**

    - `A`: (T, n, n). `B`: (T, n, m). `S0`: (n, m).

    **Returns:**

    (T, n, m): S_1, ..., S_T.
    """
    if B.ndim != 3:
        raise ValueError(f"`B` must have shape (T, n, m), got shape {B.shape}.")
    return linear_recurrence(A, B, S0)


def diagonal_linear_recurrence(a, b, x0):
    """All states of x_{k+1} = diag(a_k) x_k + b_k: the quasi-DEER linear solve.

    quasi-DEER (Gonzalez et al., NeurIPS 2024) keeps only the diagonal of each Jacobian:
    every combine is elementwise, O(n), and the scan's memory O(T n).

    **Arguments:**

    - `a`: (T, n), the diagonals. `b`: (T, n). `x0`: (n,).

    **Returns:**

    (T, n): x_1, ..., x_T.
    """
    _check(a, b, x0, "b", "x0", diagonal=True)
    P, c = _prefix(_compose_diagonal, (a, b), diagonal=True)
    return P * x0 + c


def reverse_linear_recurrence(At, g, lam_last):
    """All of lam_k = g_k + At_k lam_{k+1}, k = T-1..0, from lam_T = `lam_last`.

    The multiplier of the one-shot gradient (module docstring of `oneshot_jax._gradient`):
    with At_k = (J^{x/x}_{k+1})^T and g_k = Gamma_k^T it is the recursion that groups the
    O(T^2) chained products of eq. (17) and (20), lam_0 being grad_x0 (eq. 20). Here it is
    the forward scan of `linear_recurrence` run from the end (`reverse=True`): maps are
    composed in the order they are applied, the one at k+1 before the one at k.

    **Arguments:**

    - `At`: (T, n, n), the matrices that multiply lam_{k+1} (already transposed).
    - `g`: (T, n), or (T, n, m).
    - `lam_last`: (n,) (or (n, m)): lam_T.

    **Returns:**

    (T, n) (or (T, n, m)): lam_0, ..., lam_{T-1} (lam_T itself is not included).
    """
    _check(At, g, lam_last, "g", "lam_last", diagonal=False)
    P, c = _prefix(_compose, (At, g), reverse=True)
    return _apply(P, jnp.broadcast_to(lam_last, g.shape)) + c


def reverse_diagonal_linear_recurrence(at, g, lam_last):
    """lam_k = g_k + diag(at_k) lam_{k+1}, k = T-1..0: the diagonal form of
    `reverse_linear_recurrence`. Returns lam_0..lam_{T-1}, (T, n)."""
    _check(at, g, lam_last, "g", "lam_last", diagonal=True)
    P, c = _prefix(_compose_diagonal, (at, g), reverse=True, diagonal=True)
    return P * lam_last + c


def doubling_scan(combine, identity, elems, *, reverse=False):
    """Inclusive prefix compositions by recursive doubling (Hillis and Steele, 1986).

    The same result as `jax.lax.associative_scan(combine, elems, reverse=reverse)`, computed
    in ceil(log2 T) rounds of a `lax.fori_loop`, round d composing every element with the
    one 2^d before it (`identity` where there is none). Work O(T log T) instead of O(T), but
    `combine` is traced and compiled once instead of about 2 log2 T times, which matters when
    a combine is large (the Kalman-filter elements of `_elk.py`, with an n x n solve).

    **Arguments:**

    - `combine`: `combine(first, second)`, the composition "first, then second".
    - `identity`: an element (without the leading axis) with `combine(identity, e) == e`.
    - `elems`: a pytree of arrays with a common leading axis T.
    - `reverse`: compose from the end (element k then sees elements k..T-1).
    """
    T = jax.tree_util.tree_leaves(elems)[0].shape[0]
    rounds = int(np.ceil(np.log2(T))) if T > 1 else 0
    k = jnp.arange(T)

    def body(d, acc):
        shift = 2**d
        src = k + shift if reverse else k - shift
        valid = (src < T) if reverse else (src >= 0)
        src = jnp.clip(src, 0, T - 1)

        def earlier(a, e):
            mask = valid.reshape((T,) + (1,) * (a.ndim - 1))
            return jnp.where(mask, a[src], e)

        return combine(jax.tree_util.tree_map(earlier, acc, identity), acc)

    return jax.lax.fori_loop(0, rounds, body, elems)
