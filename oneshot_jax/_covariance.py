"""The covariance of the estimates: sigma^2 (J^T J)^+ of the data residuals at the solution.

J is the Jacobian of the weighted, scaled data residuals r = Q^{1/2} e / sqrt(N T) in the
free variables (theta's free entries, and each trajectory's free x0 entries), taken from
the solver's last linearisation when it holds one, else evaluated here (closed form,
forward sensitivities). J^T J is an arrow matrix; its inverse is formed blockwise through
the Schur complement S = A - sum_i B_i C_i^+ B_i^T, formed from the Jacobian
(`_linalg.schur_complement`: the subtraction would cancel where x0 is poorly determined)
and judged against diag(A), and the pseudo-inverses C_i^+ (`_linalg.eliminate_x0`, the
elimination the least-squares step uses), so a parameter or an initial state that does not
change the outputs is flagged as not identifiable instead of producing NaN.

`NeweyWest` replaces sigma^2 (J^T J)^+ by a sandwich that holds when the residuals are
correlated in time (a model error, coloured noise): `sandwich`.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._cost import Cost
from ._counts import integral
from ._linalg import (
    NULL_COMPONENT,
    eigh_solve,
    eliminate_x0,
    identifiable,
    identified,
    normal_blocks,
    psd_solve,
    scaled_eigh,
    schur_complement,
)
from ._problem import FitProblem, Params


def _known(covariance, p):
    """Sigma (p, p) as float64 (all inf where it has another shape: not computed) and
    the mask of its finite entries."""
    Sigma = np.asarray(covariance, np.float64)
    if Sigma.shape != (p, p):  # (not computed: `fit(covariance=None)`)
        Sigma = np.full((p, p), np.inf)
    return Sigma, np.isfinite(Sigma)


def carried_covariance(J, covariance, p):
    """J Sigma J^T (m, m) for J (m, p), the Jacobian of m quantities in theta's p free
    entries, Sigma their covariance (another shape: not computed, every entry unknown);
    inf where an entry takes an unknown entry of Sigma (J_ri Sigma_ij J_sj with J_ri,
    J_sj nonzero and Sigma_ij not finite: a parameter the data do not determine, a
    network's weights), so that a quantity of a hybrid's physical parameters alone
    takes their finite block. Of `FitResult.delta_method`."""
    Sigma, known = _known(covariance, p)
    cov = J @ np.where(known, Sigma, 0.0) @ J.T
    moves = (np.abs(J) > 0).astype(np.float64)
    cov[moves @ (~known).astype(np.float64) @ moves.T > 0] = np.inf
    return cov


def carried_variance(J, covariance, p):
    """The diagonal of `carried_covariance` for J (..., p), a row per quantity (a sample
    of an output): the variance of each, inf where unknown. Of `output_std` and
    `FitResult.predict_ahead(parameters=True)`."""
    Sigma, known = _known(covariance, p)
    moves = (np.abs(J) > 0).astype(np.float64)
    unknown = np.einsum("...p,pq,...q->...", moves, (~known).astype(np.float64), moves) > 0
    var = np.einsum("...p,pq,...q->...", J, np.where(known, Sigma, 0.0), J)
    return np.where(unknown, np.inf, np.maximum(var, 0.0))


class Covariance(NamedTuple):
    """(J^T J)^+ blocks (unscaled: multiply by sigma^2 = SSE / dof, see `FitResult`)."""

    sse: jax.Array  # ||r_data||^2 (the data part of C)
    theta: jax.Array  # (p, p)
    x0: jax.Array  # (N, m, m): each trajectory's x0 block
    theta_identifiable: jax.Array  # (p,)
    x0_identifiable: jax.Array  # (N, m)


class NeweyWest(eqx.Module):
    """Standard errors that allow for residuals correlated in time: `fit(covariance=
    NeweyWest(lags))` reports the Newey-West (Bartlett kernel) sandwich covariance of the
    estimates instead of sigma^2 (J^T J)^+.

    sigma^2 (J^T J)^+ assumes white residuals. Where they are not (a model error that
    persists over many samples, coloured measurement noise), it understates how much the
    estimates would change with another record: the sandwich estimates that variation
    from the residuals' own autocovariance up to `lags` samples (see `sandwich`; an
    initial state's own part from that autocovariance pooled over the record, as the head
    that determines it has too few samples).

    **Arguments:**

    - `lags`: the largest lag L of the residuals' autocovariance that counts (weights
        1 - l / (L + 1), l = 0..L), at most the shortest trajectory's length less one.
        None: Newey and West's (1994) rule floor(4 (T / 100)^(2/9)) for trajectories of T
        samples (T the longest one's; a shorter trajectory's autocovariance beyond its own
        length is zero), which suits short correlations only: choose L where the
        residuals' autocorrelation has died out
        (`oneshot_jax.metrics.residual_correlations`).

    Trajectories (records, or windows of a `window=` fit) count as independent of each
    other. For a theta that holds a network (an equinox module), the named parameters'
    block is their sandwich with the network's weights as nuisance parameters (the
    network's columns projected out, as for the classical covariance; its null space
    would otherwise leave the sandwich undefined). Not with `penalty` (the penalty rows
    are not observations).
    """

    lags: int | None = eqx.field(default=None, converter=integral)

    def __check_init__(self):
        lags = self.lags
        if lags is not None and (
            isinstance(lags, bool) or not isinstance(lags, (int, np.integer)) or lags < 0
        ):
            raise ValueError(f"`NeweyWest(lags=)` must be None or an integer >= 0; got {lags!r}.")

    def resolved(self, T: int, shortest: int | None = None) -> int:
        """L for trajectories of T samples (the shortest of `shortest` samples, where they
        differ: a given L must fit in every one)."""
        if self.lags is None:
            return int(np.floor(4 * (T / 100) ** (2 / 9)))
        shortest = T if shortest is None else shortest
        if self.lags > shortest - 1:
            which = f"T = {T}" if shortest == T else f"the shortest, T = {shortest}"
            raise ValueError(
                f"`NeweyWest(lags={self.lags})` exceeds a trajectory's length less one "
                f"({shortest - 1} for trajectories of {which} samples)."
            )
        return int(self.lags)


NOT_COMPUTED = "none"  # `fit(covariance=None)`: the covariance is not computed


def as_covariance(value):
    """`fit`'s `covariance` argument as None (sigma^2 (J^T J)^+), a `NeweyWest`, or
    `NOT_COMPUTED` (`None` or `"none"`: no covariance, MATLAB's `EstimateCovariance`
    false)."""
    if isinstance(value, NeweyWest):
        return value
    if value is None or (isinstance(value, str) and value == NOT_COMPUTED):
        return NOT_COMPUTED
    if isinstance(value, str) and value in ("classical", "newey_west"):
        return None if value == "classical" else NeweyWest()
    raise ValueError(
        '`covariance` must be "classical", "newey_west", a `oneshot_jax.NeweyWest(lags)` or '
        f"None (not computed); got {value!r}."
    )


def _blocks(lin, held=None):
    """(SSE, A, B, C_i, S) of the data residuals from their `Linearisation` `lin`, with the
    x0 entries `held` (N, m) (`FitProblem.x0_held`: those a record holds at its value)
    taken out of the estimate: their Jacobian columns zero, C_i's diagonal 1 there (so
    that C_i^+ keeps them apart; `_released` then sets their variance to 0)."""
    Jx = lin.Jx if held is None else lin.Jx * (1.0 - held.astype(lin.Jx.dtype))[:, None, :]
    A, B, Cb, _, _ = normal_blocks(lin.Jt, Jx, lin.r)
    if held is not None:
        Cb = Cb + jax.vmap(jnp.diag)(held.astype(Cb.dtype))
    return jnp.sum(lin.r**2), A, B, Cb, schur_complement(lin.Jt, Jx, A)


def _released(cov, held):
    """`cov` with the x0 entries `held` (N, m) known: variance and covariances 0, and
    determined (None: unchanged)."""
    if held is None:
        return cov
    keep = 1.0 - held.astype(cov.x0.dtype)
    return cov._replace(
        x0=cov.x0 * keep[:, :, None] * keep[:, None, :],
        x0_identifiable=cov.x0_identifiable | held,
    )


def covariance(problem: FitProblem, params: Params, strategy, blocks=None) -> Covariance:
    """The `Covariance` at `params`.

    `blocks`: (SSE, A, B, C_i, S) of the data residuals at `params` when the solver
    already holds them (its last linearisation; S from `_linalg.schur_complement`);
    otherwise the Jacobian is evaluated here. With `blocks`, `problem` may be None (then
    no entry is a network's: no `marginal`).
    """
    held = None if problem is None else problem.x0_held
    if blocks is None:
        blocks = _blocks(problem.jacobian(params, strategy, penalty=False), held)
    nuisance = np.asarray(() if problem is None else problem.nuisance, int)
    cov, _ = _pseudo_inverse(blocks, carry=_carries(problem))
    p = cov.theta.shape[0]
    if 0 < nuisance.size < p:
        S_inv, t_ok, _ = marginal(blocks[4], cov.theta, cov.theta_identifiable, nuisance)
        cov = cov._replace(theta=S_inv, theta_identifiable=t_ok)
    return _released(cov, held)


def _carries(problem) -> bool:
    """Whether `_pseudo_inverse` judges the initial states along theta's null directions:
    not where theta holds a network (nuisance entries)."""
    return problem is None or len(problem.nuisance) == 0


def _pseudo_inverse(blocks, carry=True):
    """The `Covariance` of (J^T J)^+ from `blocks` = (SSE, A, B, C_i, S) (no marginal
    block), and the x0 elimination (`eliminate_x0`, with C_i^+) it used. `carry`: judge
    the initial states along the null directions of theta's Schur complement too (not
    where theta holds a network: its weights' numerically null directions, which the
    named parameters' marginal block sets aside, would flag initial states the outputs
    determine; there each x0_i is judged from its own block C_i)."""
    sse, A, B, Cb, S = blocks
    p, m = A.shape[0], Cb.shape[-1]
    elim = eliminate_x0(B, Cb, pseudo_inverse=True)
    x_ok = identifiable(Cb) if m else jnp.ones(Cb.shape[:2], bool)
    if p == 0:
        return Covariance(sse, A, elim.Cinv, jnp.ones((0,), bool), x_ok), elim
    # One decomposition of S for its pseudo-inverse (`psd_solve`) and its null space
    # (`identifiable`)
    decomposition = scaled_eigh(S, jnp.diag(A))
    S_inv = eigh_solve(decomposition, jnp.eye(p, dtype=S.dtype))
    d_t, _, vecs, null, _ = decomposition
    t_ok = identified(decomposition)
    if m and carry:
        # A direction v of the null space of theta's Schur complement moves each x0_i by
        # -C_i^+ B_i^T v (the outputs unchanged): an initial state with a component
        # there is not identifiable either, though C_i alone is regular. Judged as theta
        # is, in the Jacobi scaling of J^T J (v of unit length there).
        V = jnp.where(null[None, :], vecs / d_t[:, None], 0.0)
        d_x = jnp.sqrt(jnp.diagonal(Cb, axis1=-2, axis2=-1))
        Vx = jnp.einsum("nmp,pk->nmk", elim.CinvBt, V) * d_x[..., None]
        x_ok = x_ok & ~jnp.any(jnp.abs(Vx) > NULL_COMPONENT, axis=-1)
    return Covariance(sse, S_inv, elim.covariance(S_inv), t_ok, x_ok), elim


def sandwich(problem: FitProblem, params: Params, strategy, lags: int) -> Covariance:
    """The Newey-West sandwich covariance of theta and each trajectory's x0 (`NeweyWest`),
    unscaled (`scale(..., robust=True)` applies the degrees of freedom).

    The least-squares estimate moves, to first order, by (J^T J)^+ J^T dr when the data
    residuals r of eq. (5)/(21) move by dr. With x0_i eliminated as in `eliminate_x0`
    (S = sum_i Jt~_i^T Jt~_i, Jt~_i = Jt_i - Jx_i W_i, W_i = C_i^+ B_i^T), sample k of
    trajectory i moves theta by

        psi_k = S^+ Jt~_k^T r_k,

    r_k the residual rows of sample k (its n_z outputs). With the Bartlett weights
    w_l = 1 - l / (L + 1),

        Omega_i = sum_{l=-L..L} w_|l| sum_k psi_k psi_{k-l}^T,

    the covariance of theta is Sigma_theta = sum_i Omega_i (Newey and West, Econometrica
    55, 1987; the influence form of Wooldridge's nonlinear least squares).

    x0_i moves by C_i^+ Jx_i^T dr_i - W_i dtheta. Its own part is determined by the few
    samples at the head of the trajectory, too few for products of their influences to
    estimate a variance (and their residuals are those the fit of x0 shrinks most: such
    a sandwich understates x0's spread even with white residuals). It is therefore taken
    with the
    residuals' autocovariance pooled over all samples and trajectories (stationary
    residuals): entry (o, p) of Gamma_l is sum_k r_{k,o} r_{k-l,p} over the pairs of
    samples where both outputs are measured, scaled to the record's pairs at lag l over
    its samples (an output with missing samples is not shrunk), Bartlett-weighted (with
    a full weight Q and missing samples, Gamma_l is that of the errors e, and the rows
    A_k, B_k below are Q Je_k: Q's root spreads a measured error into the row of an
    output missing at that sample):

        K(A, B) = sum_{l=-L..L} w_|l| sum_k A_k^T Gamma_l B_{k-l}   (Gamma_{-l} = Gamma_l^T),
        cov(x0_i) = C_i^+ K(Jx, Jx) C_i^+ - C_i^+ K(Jx, Jt~) S^+ W_i^T
                    - W_i S^+ K(Jt~, Jx) C_i^+ + W_i Sigma_theta W_i^T,

    Jx, Jt~ the rows of trajectory i (x0_i moves with its own residuals and, through
    theta, with every trajectory's). With white residuals and L = 0 the expectation of
    every block is that of sigma^2 (J^T J)^+.

    Where theta holds a network (`problem.nuisance`), the named parameters' block is
    their sandwich with the network's weights as nuisance parameters
    (`_marginal_sandwich`), as `covariance` reports their marginal block.

    The identifiability flags are those of `covariance`. `lags`: L (static).
    """
    held = problem.x0_held
    lin = problem.jacobian(params, strategy, penalty=False)
    blocks = _blocks(lin, held)
    S = blocks[4]
    # S^+ itself: no marginal block yet
    cov, elim = _pseudo_inverse(blocks, carry=_carries(problem))
    N, R, p = lin.Jt.shape
    T = problem.u.shape[1]
    n_z = R // T
    W = elim.CinvBt  # (N, m, p)
    Jt_elim = lin.Jt - jnp.einsum("nrm,nmp->nrp", lin.Jx, W)
    r = lin.r.reshape(N, T, n_z)
    g = jnp.einsum("ntop,nto->ntp", Jt_elim.reshape(N, T, n_z, p), r)  # (N, T, p)
    psi = g @ cov.theta
    theta = jnp.sum(_bartlett(psi, lags), axis=0)
    x0 = _x0_block(problem, lin, Jt_elim, cov.theta, elim.Cinv, W, theta, lags, params, strategy)
    nuisance = np.asarray(problem.nuisance, int)
    if 0 < nuisance.size < p:  # a network in theta: the named parameters' marginal block
        named_inv, t_ok, G = marginal(S, cov.theta, cov.theta_identifiable, nuisance)
        theta = _marginal_sandwich(theta, g, G, named_inv, nuisance, lags)
        cov = cov._replace(theta_identifiable=t_ok)
    return _released(cov._replace(theta=theta, x0=x0), held)


def _x0_block(problem, lin, Jt_elim, S_inv, C_inv, W, theta, lags: int, params, strategy):
    """cov(x0_i) of `sandwich`: x0_i's own part with the residuals' autocovariance pooled
    over the record (Gamma_l), its part through theta with the sandwich of theta."""
    N, R, m = lin.Jx.shape
    T = problem.u.shape[1]
    n_z = R // T
    r = lin.r.reshape(N, T, n_z)
    A = lin.Jx.reshape(N, T, n_z, m)
    B = Jt_elim.reshape(N, T, n_z, -1)
    Q = problem.cost.weight
    if Q is not None and Q.ndim == 2 and problem.mask is not None:
        # A full Q mixes the outputs: its root spreads a measured error into the row of
        # one missing at that sample, so "the pairs where both outputs are measured" are
        # those of the errors e themselves. Gamma is theirs, and Q moves to the rows:
        # sum_k (Q Je_k)^T Gamma_e (Q Je_k-l), which is the weighted form's where nothing
        # is missing (r = Q^{1/2} e), whatever Q's square root.
        plain = eqx.tree_at(
            lambda p: p.cost, problem, Cost(None, None, problem.cost.penalty_weight)
        )
        lin_e = plain.jacobian(params, strategy, penalty=False)
        r = lin_e.r.reshape(N, T, n_z)
        A = jnp.einsum("op,ntpm->ntom", Q, lin_e.Jx.reshape(N, T, n_z, m))
        Jt_e = lin_e.Jt - jnp.einsum("nrm,nmp->nrp", lin_e.Jx, W)
        B = jnp.einsum("op,ntpq->ntoq", Q, Jt_e.reshape(N, T, n_z, -1))
    # The samples behind Gamma: the measured output entries the loss sees, per output.
    seen = jnp.ones((N, T, n_z), bool)
    if problem.mask is not None:
        out = problem.mask.outputs
        seen = jnp.broadcast_to(out if out.ndim == 3 else out[..., None], seen.shape) > 0
    observed = problem.cost.observed()
    if observed is not None:
        seen = seen & observed
    k = jnp.arange(T)
    present = jnp.ones((N, T), r.dtype) if problem.mask is None else problem.mask.samples
    present = jnp.broadcast_to(present, (N, T)).astype(r.dtype)
    s = seen.astype(r.dtype)

    def shift(a, lg):  # a_{k-l}, zero before the start
        mask = (k >= lg).reshape((1, T) + (1,) * (a.ndim - 2))
        return jnp.where(mask, jnp.roll(a, lg, axis=1), 0.0)

    def autocov(lg):  # Gamma_l: each pair of outputs over the pairs of samples it has
        # (a missing sample is no zero residual), scaled as the complete record's
        # sum / its samples: (pairs in the records) / (pairs seen) / (samples)
        num = jnp.einsum("nto,ntp->op", r, shift(r, lg))
        seen_pairs = jnp.einsum("nto,ntp->op", s, shift(s, lg))
        pairs = jnp.sum(present * shift(present, lg))
        return num * pairs / jnp.maximum(seen_pairs, 1.0) / jnp.maximum(jnp.sum(present), 1.0)

    def K(lg, gamma, X, Y):  # sum_k X_k^T Gamma_l Y_{k-l} + (its transpose pair)
        out = jnp.einsum("ntoa,op,ntpb->nab", X, gamma, shift(Y, lg))
        return out + jnp.einsum("ntoa,op,ntpb->nab", shift(X, lg), gamma.T, Y)

    def lag(lg, acc):
        gamma = autocov(lg)
        w = 1.0 - lg / (lags + 1.0)
        return acc[0] + w * K(lg, gamma, A, A), acc[1] + w * K(lg, gamma, A, B)

    gamma0 = autocov(0)
    own = jnp.einsum("ntoa,op,ntpb->nab", A, gamma0, A)
    cross = jnp.einsum("ntoa,op,ntpb->nab", A, gamma0, B)
    own, cross = jax.lax.fori_loop(1, lags + 1, lag, (own, cross))
    own = C_inv @ own @ C_inv
    mix = C_inv @ cross @ S_inv @ jnp.swapaxes(W, 1, 2)  # C^+ K(Jx, Jt~) S^+ W^T
    through = jnp.einsum("nmp,pq,nlq->nml", W, theta, W)
    x0 = own - mix - jnp.swapaxes(mix, 1, 2) + through
    return 0.5 * (x0 + jnp.swapaxes(x0, 1, 2))


def _bartlett(v, lags: int):
    """Omega_i = sum_{l=-L..L} (1 - |l| / (L + 1)) sum_k v_k v_{k-l}^T per trajectory i
    (`v`: (N, T, a); L = `lags`, static): the Newey-West long-run covariance of `sandwich`."""
    T = v.shape[1]
    k = jnp.arange(T)

    def lag(lg, omega):
        shifted = jnp.where((k >= lg)[None, :, None], jnp.roll(v, lg, axis=1), 0.0)
        gamma = jnp.einsum("nta,ntb->nab", v, shifted)
        w = 1.0 - lg / (lags + 1.0)
        return omega + w * (gamma + jnp.swapaxes(gamma, 1, 2))

    omega = jnp.einsum("nta,ntb->nab", v, v)
    return jax.lax.fori_loop(1, lags + 1, lag, omega)


def _marginal_sandwich(theta, g, G, marginal_inv, nuisance, lags: int):
    """`theta` (the sandwich of S^+) with the named parameters' block replaced by their
    sandwich with a network's weights as nuisance parameters, the robust twin of
    `marginal`: sample k moves the named parameters by

        psi_k = (S_pp - S_pn S_nn^+ S_np)^+ (g_pk - S_pn S_nn^+ g_nk),

    g_k = Jt~_k^T r_k (the x0-eliminated Jacobian's rows of sample k times its
    residuals; p: named, n: the network's entries), i.e. the influence of the named
    columns with the network's range projected out (J_p^T (I - P_n) dr, as in
    `marginal`). Where S is regular this equals the named rows of S^{-1} g_k (the
    block-inverse formula), so the block is the full sandwich's; where the network has a
    null space, it is formed with the projection that `marginal` uses for the classical
    block (the network's null space judged within S_nn, not through S^+'s eigenvectors of
    the whole S), so that both covariances of a hybrid use one projection.
    `G`: S_nn^+ S_np; `marginal_inv`: S^+ with the named block the marginal inverse (both
    from `marginal`)."""
    named = np.setdiff1d(np.arange(theta.shape[0]), nuisance)
    g_named = g[..., named] - g[..., nuisance] @ G
    psi = g_named @ marginal_inv[np.ix_(named, named)]
    block = jnp.sum(_bartlett(psi, lags), axis=0)
    return theta.at[np.ix_(named, named)].set(block)


def marginal(S, S_inv, t_ok, nuisance):
    """The named parameters' covariance with a network's weights as nuisance parameters:

        (S_pp - S_pn S_nn^+ S_np)^+ = (J_p^T (I - P_n) J_p)^+,

    J_p, J_n the columns of the named parameters and of the network (after the x0
    elimination), P_n the projector onto the range of J_n. A network has directions that
    leave its output unchanged (its null space): they make S singular, and the
    Moore-Penrose S^+ then mixes them into every parameter's block. Eliminated through
    S_nn^+ instead, they drop out, and a named parameter is identifiable exactly when its
    effect on the outputs is not one the network can produce (then its std is finite).
    Where S is regular this equals the block of S^{-1} (the block-inverse formula), so
    the fit's other parameters are reported as before.

    **Arguments:**

    - `S`: (p, p) the Schur complement of the x0 blocks in J^T J (`eliminate_x0`).
    - `S_inv`, `t_ok`: S^+ and per-entry identifiability from S.
    - `nuisance`: the positions of the network's entries among the p (host array).

    **Returns:** `(S_inv, t_ok, G)`: S^+ and the flags with the named parameters' block
    and flags replaced, and G = S_nn^+ S_np (the network's least-squares response to the
    named parameters, for `_marginal_sandwich`).
    """
    p = S.shape[0]
    named = np.setdiff1d(np.arange(p), nuisance)
    S_nn = S[np.ix_(nuisance, nuisance)]
    S_pn = S[np.ix_(named, nuisance)]
    G = psd_solve(S_nn, S_pn.T)  # S_nn^+ S_np
    S_marginal = S[np.ix_(named, named)] - S_pn @ G
    S_marginal = 0.5 * (S_marginal + S_marginal.T)
    block = psd_solve(S_marginal, jnp.eye(named.size, dtype=S.dtype))
    S_inv = S_inv.at[np.ix_(named, named)].set(block)
    # Null where the network reproduces a named column up to round-off of the column
    # itself: S_marginal judged in the scaling of S_pp (its own diagonal would make a
    # round-off remainder of a 1 x 1 block look regular).
    S_pp_diag = jnp.diagonal(S)[named]
    return S_inv, t_ok.at[named].set(identifiable(S_marginal, S_pp_diag)), G


class Scaled(NamedTuple):
    """sigma^2 (J^T J)^+, with inf where a variable is not identifiable, and the standard
    errors (the square roots of its diagonal)."""

    theta: jax.Array  # (p, p) covariance of theta's free entries
    x0: jax.Array  # (N, m, m) covariance of each trajectory's free x0 entries
    theta_identifiable: jax.Array
    x0_identifiable: jax.Array
    theta_std: jax.Array  # (p,)
    x0_std: jax.Array  # (N, m)
    dof: jax.Array  # n_obs - n_free: sigma^2 is unknown (every error inf) where it is <= 0


def scale(cov: Covariance, e, cost=None, robust: bool = False, held=None) -> Scaled:
    """Multiply by sigma^2 = SSE / dof (dof = n_obs - n_free, n_obs the observations among
    the finite entries of the residuals `e`, `Cost.observations` of the problem's `cost`:
    an output of zero weight adds none, a singular weight matrix its rank per sample), or
    for a `sandwich` (`robust`) by n_obs / dof (the small-sample factor of the sandwich);
    traced, inside the compiled call that made `cov`.

    With J = Q^{1/2} J_e / sqrt(N T), sigma^2 (J_e^T Q J_e)^{-1} = (SSE_r / dof) (J^T J)^{-1}.
    A variable outside the identifiable set gets an infinite variance, and so does every
    variable when there are no more observations than free variables (dof <= 0). `held`:
    the x0 entries a record holds (`FitProblem.x0_held`), not free, or None.
    """
    t_ok, x_ok = cov.theta_identifiable, cov.x0_identifiable
    seen = jnp.isfinite(e)
    # An output reproduced exactly at every sample (a logged setpoint the model returns)
    # has no noise: its zeros are no observations of sigma^2 (they would shrink it), unless
    # every output is (a zero residual: sigma^2 = 0).
    over = tuple(range(e.ndim - 1))
    measured = jnp.any(seen, axis=over)
    exact = measured & jnp.all((e == 0) | ~seen, axis=over)
    seen = seen & ~(exact & jnp.any(measured & ~exact))
    n_obs = jnp.sum(seen) if cost is None else cost.observations(seen)
    dof = n_obs - (t_ok.size + x_ok.size - (0 if held is None else jnp.sum(held)))
    known = dof > 0
    top = n_obs.astype(cov.sse.dtype) if robust else cov.sse
    s2 = jnp.where(known, top / jnp.where(known, dof, 1).astype(cov.sse.dtype), jnp.inf)
    theta = jnp.where(known & t_ok[:, None] & t_ok[None, :], cov.theta * s2, jnp.inf)
    x0 = jnp.where(known & x_ok[:, :, None] & x_ok[:, None, :], cov.x0 * s2, jnp.inf)

    def std(c):
        return jnp.sqrt(jnp.maximum(jnp.diagonal(c, axis1=-2, axis2=-1), 0.0))

    return Scaled(theta, x0, t_ok, x_ok, std(theta), std(x0), dof)
