r"""Hybrid fits whose physics stays identifiable.

A learned term that sees more than the effect it stands for (a network fed the whole
state, r(q, q'), where the missing effect is a damping) can explain part of what the
physical parameters explain: a term in q trades with w0sq sin q, the data cannot tell
them apart, and a joint fit of eq. (5) leaves the physical parameters wherever the
solver's path ends. Two remedies, both on the public `fit`:

- `fit_orthogonal`: orthogonal-by-construction augmentation (Gyorok, Hoekstra, Kon,
    Beintema, Schoukens, Toth, arXiv 2511.01321, 2025) as a penalty. The learned terms'
    contribution to the output, d = yhat(theta) - yhat(theta with the learned terms
    switched off), is penalised by lambda ||Q^T W^{1/2} d||^2, Q an orthonormal basis of
    the weighted output sensitivities W^{1/2} d yhat / d theta_phys: at the optimum the
    network's contribution has no component that a physical parameter could explain.
    The fit is an ordinary fit of an augmented `Model` (the model, a copy run with the
    learned terms off, and an accumulator of Q_k^T W^{1/2} d_k over the samples, read
    at the last sample), so the rollout, the one-shot gradient of eq. (17)/(20) and the
    least-squares solvers apply unchanged and exactly; Q is data (extra input columns),
    computed from forward-mode autodiff sensitivities of `simulate` and held fixed for a
    round of the fit, then recomputed at the new estimate (a fixed-point iteration over
    rounds).
- `fit_physics_first`: two fits, the physical model alone (the learned terms switched
    off and held), then the learned terms with the physical parameters held. Its
    physical estimates are those of the physics alone (the learned terms off; a model
    written without them reaches the same point to the solver's tolerance, its round-off
    on another path). For an output-additive
    augmentation y = y_p(theta_phys) + P Delta, P the projector off S = d y_p / d
    theta_phys held fixed, the normal equations of theta_phys read
    S^T (y - y_p - P Delta) = S^T (y - y_p) = 0, those of the physics alone: there the
    two remedies agree. For a learned term inside the dynamics they differ: the
    orthogonal fit lets the network explain what is orthogonal to the sensitivities while
    the physics moves, the two-stage fit estimates the physics with the whole unmodelled
    effect in its residuals.
"""

import math
import numbers
import warnings
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from ._caller_warnings import at_caller
from ._checks import as_float, check_data, is_weak
from ._continuation import check_fit_keywords
from ._counts import integral, real
from ._fit import fit
from ._fit_result import FitResult
from ._model import Model
from ._simulate import loss, simulate
from ._solver_arg import as_solvers
from ._starts import as_multistart


class PhysicsFirst(eqx.Module):
    """What `fit_physics_first` returns.

    **Fields:**

    - `physics`: the `FitResult` of stage 1, the physical model alone (the learned terms
        switched off and held): the physical estimates and their standard errors.
    - `result`: the `FitResult` of stage 2, the hybrid model: the learned terms fitted
        with the physical parameters held at `physics`'s values (so they are equal).
    """

    physics: FitResult
    result: FitResult

    @property
    def success(self) -> bool:
        """Whether both stages reached their stopping test (each its own)."""
        return bool(self.physics.success) and bool(self.result.success)

    def __str__(self):
        rows = "\n".join(
            f"{name:>8}  {float(r.loss):>12.5g}  {r.status}"
            for name, r in (("physics", self.physics), ("hybrid", self.result))
        )
        head = f"{'stage':>8}  {'loss':>12}  stop"
        note = (
            "The hybrid stage holds the physical parameters (fixed below): their standard "
            "errors are those of the physics stage (the field `physics`)."
        )
        return f"Physics first, then the learned terms:\n{head}\n{rows}\n{note}\n\n{self.result}"

    __repr__ = __str__


def _learned_keys(theta0, learned):
    if not isinstance(theta0, Mapping):
        raise TypeError(
            "`theta0` must be a dict of the physical parameters and the learned terms, "
            f"e.g. {{'w0sq': 9.0, 'r': MLP(...)}}, got {type(theta0).__name__}."
        )
    keys = (learned,) if isinstance(learned, str) else learned
    if not isinstance(keys, (tuple, list)) or not keys:
        raise TypeError(f"`learned` must be a key of theta0 or a tuple of keys, got {learned!r}.")
    keys = tuple(keys)
    for k in keys:
        if not isinstance(k, str) or k not in theta0:
            raise ValueError(
                f"`learned` names {k!r}, which is not a key of theta0 "
                f"(its keys: {sorted(map(str, theta0))})."
            )
    if len(set(keys)) != len(keys):
        raise ValueError(f"`learned` names a key twice: {keys!r}.")
    for k in keys:
        leaves = jax.tree_util.tree_leaves(theta0[k])
        if not any(eqx.is_inexact_array(a) or is_weak(a) for a in leaves):  # (as `fit` reads)
            raise ValueError(f"`learned` names {k!r}, which holds no floating array to fit.")
    if all(np.ndim(a) == 0 for k in keys for a in jax.tree_util.tree_leaves(theta0[k])):
        raise ValueError(
            f"`learned` names only single numbers ({', '.join(map(repr, keys))}): the learned "
            "terms are networks (`MLP`), `Dictionary` terms or arrays of weights, switched "
            "off at zero; a single number is a physical parameter (name the key of the "
            "network)."
        )
    physical = [k for k in theta0 if k not in keys]
    if not any(
        eqx.is_inexact_array(a) or is_weak(a)
        for k in physical
        for a in jax.tree_util.tree_leaves(theta0[k])
    ):
        raise ValueError(
            "`learned` names every parameter of theta0: stage 1 would have no physical "
            "parameter to fit."
        )
    return keys, physical


def _fixed(theta0, fixed):
    if fixed is None:
        return {}
    if not isinstance(fixed, Mapping):
        raise TypeError(
            "`fixed` must be None or a dict over theta0's keys (a boolean or a pytree of "
            f"booleans per key), got {type(fixed).__name__}."
        )
    extra = [k for k in fixed if k not in theta0]
    if extra:
        raise ValueError(f"`fixed` has keys that theta0 does not have: {extra!r}.")
    return dict(fixed)


def _switched_off(term):
    """The learned term with every floating array at zero (its output zero for `MLP` and
    `Dictionary`, whose output is linear in the last layer or the coefficients);
    traceable."""
    return jax.tree_util.tree_map(
        lambda a: jnp.zeros_like(a) if eqx.is_inexact_array(a) else a, term
    )


def fit_physics_first(
    model,
    theta0: PyTree,
    x0: Float[ArrayLike, "*N n_x"],
    u: Float[ArrayLike, "*N T n_u"],
    z: Float[ArrayLike, "*N T n_z"],
    *,
    learned="r",
    solver="levenberg_marquardt",
    network_solver=None,
    fixed=None,
    multistart: bool | dict = False,
    **kwargs,
) -> PhysicsFirst:
    """A hybrid fit whose physical estimates are those of the physical model alone.

    Two fits of the multi-step cost C of eq. (5)/(21) with `fit`:

    1. the physical model alone: every learned term named by `learned` switched off
        (its floating arrays at zero: the output of an `MLP` or a `Dictionary` is then
        exactly zero) and held; the other entries of theta0 fitted;
    2. the learned terms, started from theta0's values, with every physical parameter
        held at stage 1's estimate and x0 started from stage 1's.

    The physical estimates of the hybrid are stage 1's, exactly, whatever the learned
    terms see (a network fed the whole state cannot absorb part of the restoring force).
    Stage 2 starts at stage 1's loss only when the learned terms start with a zero output
    (an `MLP` with `zero_last=True`, a `Dictionary` of zero coefficients); started
    elsewhere, it can end above stage 1's loss (see `success`). For a learned term added
    to the output this is
    the estimate of orthogonal-by-construction augmentation (Gyorok et al., arXiv
    2511.01321, 2025; see `fit_orthogonal`). The price: the physics is estimated with
    the unmodelled effect in its residuals (the physical model's own bias).

    **Arguments:**

    - `model`, `x0`, `u`, `z`: as for `fit`.
    - `theta0`: a dict of the physical parameters and the learned terms, e.g.
        `{"w0sq": 8.0, "b": 0.2, "r": MLP(...)}`.
    - `learned`: the key, or a tuple of keys, of theta0 that hold the learned terms.
    - `solver`: stage 1's solver (any value of `fit`'s `solver`).
    - `network_solver`: stage 2's solver; None uses `solver`.
    - `fixed`: None, or a dict over theta0's keys as `fit`'s `fixed`: physical entries
        held in stage 1, parts of the learned terms held in stage 2.
    - `multistart`: `fit`'s `multistart`, for stage 1 only (starts of the physical
        parameters, or True with a leading axis of starts on every physical leaf).
    - `**kwargs`: every other keyword of `fit` (`weight`, `penalty`, `constraints`,
        `estimate_x0`, `window`, `t`, ...), passed to both stages.

    **Returns:**

    A `PhysicsFirst`: `physics` (stage 1's `FitResult`) and `result` (stage 2's, the
    hybrid, whose physical entries equal stage 1's); `success` when both stages
    succeeded.
    """
    check_fit_keywords(kwargs, "fit_physics_first")
    if network_solver is not None:  # (checked before stage 1 runs, not after it)
        try:
            as_solvers(network_solver)
        except (TypeError, ValueError) as err:
            raise type(err)(f"`network_solver`: {err}") from None
    keys, _ = _learned_keys(theta0, learned)
    held = _fixed(theta0, fixed)
    multistart = as_multistart(multistart, theta0)
    if multistart is True:
        # The physical leaves carry the starts, the learned terms (switched off in stage
        # 1) none: the dict form of `fit`, with each physical entry's first start in theta.
        multistart = {k: theta0[k] for k in theta0 if k not in keys}
        for path, leaf in jax.tree_util.tree_flatten_with_path(multistart)[0]:
            if np.ndim(leaf) == 0:
                raise ValueError(
                    "with `multistart=True` every physical leaf of `theta0` needs a leading "
                    f"axis of starts (the learned terms none); theta0"
                    f"{jax.tree_util.keystr(path)} is a scalar. To start some physical "
                    'parameters only, pass them as `multistart={"name": starts, ...}`.'
                )
        theta0 = {
            k: v if k in keys else jax.tree_util.tree_map(lambda a: np.asarray(a)[0], v)
            for k, v in theta0.items()
        }
    theta_phys = _off(theta0, keys)
    if multistart is not False and isinstance(multistart, Mapping):
        wrong = [k for k in multistart if k in keys]
        if wrong:
            raise ValueError(
                f"`multistart` has starts of the learned terms {wrong!r}: stage 1 holds them."
            )
    with at_caller(__file__):  # (both stages' warnings, at the caller's line)
        physics = fit(
            model,
            theta_phys,
            x0,
            u,
            z,
            solver=solver,
            fixed={k: (True if k in keys else held.get(k, False)) for k in theta0},
            multistart=multistart,
            **kwargs,
        )
        theta_hybrid = {k: (theta0[k] if k in keys else physics.theta[k]) for k in theta0}
        result = fit(
            model,
            theta_hybrid,
            physics.x0,
            u,
            z,
            solver=solver if network_solver is None else network_solver,
            fixed={k: (held.get(k, False) if k in keys else True) for k in theta0},
            **kwargs,
        )
    return PhysicsFirst(physics=physics, result=result)


class Round(eqx.Module):
    """One round of `fit_orthogonal` (the basis Q fixed, then a fit).

    **Fields:**

    - `physics`: the physical parameters at the end of the round (a dict).
    - `loss`: the data cost C of eq. (5) at the end of the round (the penalty excluded).
    - `projection`: ||Q^T W^{1/2} d|| / ||W^{1/2} d||, the share of the learned terms'
        output contribution d along the physical sensitivities (0: orthogonal), both at
        the end of the round (Q recomputed there: the basis the round held moves with
        the network).
    - `change`: the largest relative change of a physical parameter in the round.
    - `moved`: the largest change of a physical parameter in the round in its standard
        errors (those of the round's fit; inf where one is not finite; an entry held by
        `fixed` does not count).
    - `absorbed`: the physics the learned terms carry at the end of the round: the
        largest change of a physical parameter that would explain d's part along the
        sensitivities (least squares), in its standard errors (inf where one is not
        finite, or the sensitivities are not).
    - `status`: the round's fit's stop reason.
    """

    physics: dict
    loss: float
    projection: float
    change: float
    moved: float
    absorbed: float
    status: str

    def _row(self):
        """The round's row of `Orthogonal`'s table (loss, projection, change, moved SE,
        absorbed SE, stop)."""
        return (
            f"{self.loss:>12.5g}  {self.projection:>10.3g}  {self.change:>10.3g}  "
            f"{self.moved:>10.3g}  {self.absorbed:>11.3g}  {self.status}"
        )

    def __str__(self):
        return (
            f"Round: loss {self.loss:.5g}, projection {self.projection:.3g}, change "
            f"{self.change:.3g}, moved {self.moved:.3g} SE, absorbed {self.absorbed:.3g} SE, "
            f"stop {self.status}"
        )

    __repr__ = __str__


class Orthogonal(eqx.Module):
    """What `fit_orthogonal` returns.

    **Fields:**

    - `theta`, `x0`: the estimates for the hybrid `model` as given (x0 of shape (n_x,)).
    - `loss`: the data cost C of eq. (5) at them (the penalty excluded).
    - `rounds`: a `Round` per round (physical parameters, loss, projection, changes,
        stop).
    - `result`: the last round's `FitResult`, of the augmented model (its `x0`, `residuals`
        and outputs are the augmented ones; its `std` is that of the penalised fit).
    - `converged`: whether the physical parameters moved by less than `stol` standard
        errors, or by less than `rtol` relative, in the last round, the physics the
        network carries at its end (`Round.absorbed`) is below `stol` standard errors
        or `rtol` relative to the parameters, and that round's fit succeeded (a fit that stops
        short of its optimum for the round's basis, on its step budget or with its
        network's units saturated, moves them little without having settled them).
    """

    theta: PyTree
    x0: np.ndarray
    loss: float
    rounds: tuple
    result: FitResult
    converged: bool

    @property
    def success(self) -> bool:
        """Whether the rounds converged and the last round's fit succeeded."""
        return bool(self.converged) and bool(self.result.success)

    def __str__(self):
        head = (
            f"{'round':>5}  {'loss':>12}  {'projection':>10}  {'change':>10}  {'moved SE':>10}"
            f"  {'absorbed SE':>11}"
            "  stop"
        )
        rows = "\n".join(f"{i:>5}  {r._row()}" for i, r in enumerate(self.rounds))
        state = "converged" if self.converged else "not converged"
        return f"Orthogonal augmentation, {len(self.rounds)} rounds ({state}):\n{head}\n{rows}"

    __repr__ = __str__


def _off(theta, keys):
    """theta with the learned terms switched off (`_switched_off`)."""
    return {k: (_switched_off(v) if k in keys else v) for k, v in theta.items()}


def _augmented(model, keys, n_x, n_u, n_z, p):
    """The model, its copy with the learned terms off (as the offset dl of the states,
    x + dl, from dl = 0) and the accumulator s of Q_k^T W^{1/2} d_k; the extra outputs
    s + Q_k^T W^{1/2} d_k (the sum through sample k). The inputs: u, then M_k = W^{1/2}
    Q_k flattened (n_z * p)."""

    def parts(xa, ua):
        return xa[:n_x], xa[n_x : 2 * n_x], xa[2 * n_x :], ua[..., :n_u], ua[..., n_u:]

    def projected(x, dl, u, m, theta):
        d = model.observe(x, u, theta) - model.observe(x + dl, u, _off(theta, keys))
        return m.reshape(n_z, p).T @ d

    def step(xa, ua, theta):
        x, dl, s, us, m = parts(xa, ua)
        u_k, m_k = (us[0], m[0]) if model.input == "foh" else (us, m)
        x_next = model.step(x, us, theta)
        off_next = model.step(x + dl, us, _off(theta, keys))
        return jnp.concatenate([x_next, off_next - x_next, s + projected(x, dl, u_k, m_k, theta)])

    def observe(xa, ua, theta):
        x, dl, s, u, m = parts(xa, ua)
        return jnp.concatenate([model.observe(x, u, theta), s + projected(x, dl, u, m, theta)])

    return Model(step, observe, input=model.input)


def _free_physics(theta, keys, held):
    """The physical entries that the fit moves: keys not learned, not held as a whole."""
    return [k for k in theta if k not in keys and held.get(k, False) is not True]


def _sensitivities(model, theta, x0, u, names, root):
    """Sw = W^{1/2} d yhat_k / d theta_phys (T n_z, p): the weighted output sensitivities
    to the physical parameters over the record (forward-mode autodiff of `simulate`)."""
    phys = {k: theta[k] for k in names}
    dyn, static = eqx.partition(phys, eqx.is_inexact_array)

    def outputs(dyn):
        return simulate(model, {**theta, **eqx.combine(dyn, static)}, x0, u)[1]

    jac = jax.jacfwd(outputs)(dyn)
    T, n_z = np.shape(u)[0], root.shape[0]
    cols = [np.asarray(j).reshape(T, n_z, -1) for j in jax.tree_util.tree_leaves(jac)]
    S = np.concatenate(cols, axis=2)
    return np.einsum("ji,tjp->tip", root, S).reshape(T * n_z, -1)


def _orthonormal(sw, root):
    """M_k = W^{1/2} Q_k (T, n_z, p) of `_basis` from the weighted sensitivities `sw`
    (T n_z, p): Q from their QR factorisation where R's diagonal has no entry below 1e-10
    of its largest (full rank); else their left singular vectors of a singular value
    above 1e-10 of the largest, the other columns zero. (The QR's Q with its columns
    zeroed where R's diagonal was small spanned the wrong space where a zero or
    dependent column came before others: an input gain written ga * gb left 20 % of
    w0sq's sensitivity outside it.) Non-finite sensitivities give a non-finite Q."""
    n_z = root.shape[0]
    q, r = np.linalg.qr(sw)
    diag = np.abs(np.diag(r))
    small = diag <= 1e-10 * max(diag.max(initial=0.0), np.finfo(float).tiny)
    if np.all(np.isfinite(sw)) and small.any():
        q, sv, _ = np.linalg.svd(sw, full_matrices=False)
        q = q * (sv > 1e-10 * max(sv.max(initial=0.0), np.finfo(float).tiny))
    return np.einsum("ij,tjp->tip", root, q.reshape(-1, n_z, q.shape[-1]))


def _basis(model, theta, x0, u, names, root):
    """M_k = W^{1/2} Q_k (T, n_z, p): Q an orthonormal basis of the weighted output
    sensitivities W^{1/2} d yhat_k / d theta_phys over the record (`_sensitivities`);
    columns beyond the sensitivities' rank are zero."""
    return _orthonormal(_sensitivities(model, theta, x0, u, names, root), root)


def _absorbed(sw, dw, std, values, free):
    """The change of the free physical parameters (`values` where `free`) whose
    sensitivities (`sw`'s columns, T n_z) explain the weighted learned contribution `dw`
    (T n_z,) best (least squares): its largest entry in standard errors `std` (inf where
    one is not finite) and relative to the value; inf, inf where the sensitivities are
    not finite."""
    if not np.all(np.isfinite(sw)):
        return math.inf, math.inf
    coef = np.abs(np.linalg.lstsq(sw[:, free], dw, rcond=None)[0])
    std, values = std[free], values[free]
    ok = np.isfinite(std) & (std > 0)
    se = np.where(ok, coef / np.where(ok, std, 1.0), np.inf)
    rel = coef / np.maximum(np.abs(values), 1e-12)
    return float(np.max(se, initial=0.0)), float(np.max(rel, initial=0.0))


def _flat(theta, names):
    """The floating entries of theta's `names` as one vector."""
    phys = eqx.filter({k: theta[k] for k in names}, eqx.is_inexact_array)
    leaves = [np.ravel(np.asarray(a, float)) for a in jax.tree_util.tree_leaves(phys)]
    return np.concatenate(leaves) if leaves else np.zeros(0)


_REFUSED = ("aggregate", "window", "t", "multistart", "validation", "penalty", "missing")


def fit_orthogonal(
    model,
    theta0: PyTree,
    x0: Float[ArrayLike, " n_x"],
    u: Float[ArrayLike, "T n_u"],
    z: Float[ArrayLike, "T n_z"],
    *,
    learned="r",
    strength: float = 100.0,
    rounds: int = 10,
    stol: float = 0.1,
    rtol: float = 1e-4,
    solver="levenberg_marquardt",
    weight=None,
    fixed=None,
    estimate_x0=True,
    **kwargs,
) -> Orthogonal:
    r"""A hybrid fit whose learned terms explain only what the physics cannot.

    Orthogonal-by-construction augmentation (Gyorok, Hoekstra, Kon, Beintema, Schoukens,
    Toth, arXiv 2511.01321, 2025) as a penalty on the multi-step cost of eq. (5):

        C_orth = (1/T) [ sum_k e_k^T W e_k + strength ||Q^T W^{1/2} d||^2 ],

    d_k = yhat_k(theta) - yhat_k(theta with the learned terms switched off) the learned
    terms' contribution to the output, Q an orthonormal basis of the weighted output
    sensitivities W^{1/2} d yhat_k / d theta_phys of the physical parameters (every free
    entry of theta0 outside `learned`). At the optimum of a large `strength` the learned
    contribution has no component that a physical parameter could explain, so the
    physics cannot be absorbed by a network that sees the whole state. The converse
    holds too: the part of a missing effect that lies along the physical sensitivities
    goes to the physics, which is then biased (a model without a damping term, its
    damping left to the network), beyond what its standard errors measure (see the
    guide on bad minima and identifiable hybrids).

    Each round computes Q at the current estimate (forward-mode autodiff of `simulate`,
    one column per physical parameter; these sensitivities are not on the closed-form
    path) and fits C_orth with Q held fixed; the next round starts there. The penalty is
    exact inside a round: the fit is one of an augmented `Model` (the model, its copy
    with the learned terms off, an accumulator of Q_k^T W^{1/2} d_k), so its gradient
    and residual Jacobian are the one-shot closed form of eq. (17)/(20); the copy
    doubles the state, so a round costs about two plain fits. Rounds stop after one
    whose fit succeeded, in which no physical parameter moved by more than `stol` of
    its standard errors (or none by more than `rtol`, relative), and at whose end, Q
    recomputed there, the learned contribution along the sensitivities would move none
    by more than `stol` of its standard errors (`Round.absorbed`; or `rtol`, relative);
    or after `rounds`.

    **Arguments:**

    - `model`, `x0`, `u`, `z`: as for `fit`, one record: x0 (n_x,), u (T, n_u), z
        (T, n_z) without missing samples. A model with time stamps (`timed`) is not
        supported.
    - `theta0`: a dict of the physical parameters and the learned terms, e.g.
        `{"w0sq": 8.0, "b": 0.2, "r": MLP(...)}`.
    - `learned`: the key, or a tuple of keys, of theta0 that hold the learned terms
        (switched off: their floating arrays at zero, which makes an `MLP` or a
        `Dictionary` output exactly zero).
    - `strength`: lambda > 0 of the penalty (its residuals are sqrt(lambda / T) Q^T
        W^{1/2} d).
    - `rounds`: the largest number of rounds (>= 1). The rounds contract slowly near
        the end (`result.rounds` gives each round's move in standard errors), so the
        default leaves room beyond the few a converging fit takes.
    - `stol`: the change of the physical parameters in a round, in their standard
        errors, below which the rounds have converged (> 0); the fits' own statistical
        stop (`stol` of the least-squares solvers) leaves them about that precise.
    - `rtol`: the relative change below which the rounds have converged too (> 0; for
        parameters without a finite standard error).
    - `solver`, `weight`, `fixed`, `estimate_x0`: as for `fit` (`fixed` a dict over
        theta0's keys; a key held as a whole is not among the physical parameters of Q;
        `estimate_x0` a boolean or an (n_x,) mask; `weight` a given Q, not "noise").
    - `**kwargs`: other keywords of `fit` (`constraints`, `progress`, `history`,
        `units`, ...), passed to every round; `aggregate`, `window`, `t`, `multistart`,
        `validation`, `penalty` and `missing` are refused.

    **Returns:**

    An `Orthogonal`: `theta` and `x0` for `model`, the data cost `loss`, one `Round`
    per round (with `projection`, the share of the learned contribution along the
    physical sensitivities), the last round's `FitResult` and `converged`; `success`
    when the rounds converged and the last fit succeeded.
    """
    check_fit_keywords(kwargs, "fit_orthogonal")
    keys, _ = _learned_keys(theta0, learned)
    held = _fixed(theta0, fixed)
    refused = sorted(k for k in kwargs if k in _REFUSED)
    if refused:
        raise ValueError(f"`fit_orthogonal` does not take {refused}: fit one plain record.")
    strength, rounds = real(strength), integral(rounds)
    if (
        isinstance(strength, (bool, np.bool_))
        or not isinstance(strength, numbers.Real)
        or not 0 < strength < math.inf
    ):
        raise ValueError(f"`strength` must be a finite number > 0, got {strength!r}.")
    if isinstance(rounds, bool) or not isinstance(rounds, numbers.Integral) or rounds < 1:
        raise ValueError(f"`rounds` must be an integer >= 1, got {rounds!r}.")
    if isinstance(weight, str):
        raise ValueError(
            f"`weight` must be Q (a vector of per-output weights or a matrix): "
            f"`fit_orthogonal` does not estimate it, got {weight!r}; fit with "
            "`weight='noise'` first and pass its `result.weight`."
        )
    for name, value in (("stol", stol), ("rtol", rtol)):
        if not isinstance(value, numbers.Real) or not 0 < value < math.inf:
            raise ValueError(f"`{name}` must be a finite number > 0, got {value!r}.")
    if not isinstance(model, Model):
        raise TypeError(f"`model` must be a `Model`, got {type(model).__name__}.")
    if model.timed:
        raise ValueError("`model` is timed (dt=None): `fit_orthogonal` needs a fixed dt.")
    x0, u, z = (
        np.asarray(as_float(a, name, measured=name == "z"), dtype=float)
        for a, name in ((x0, "x0"), (u, "u"), (z, "z"))
    )
    if x0.ndim != 1:
        raise ValueError(f"`x0` must have shape (n_x,) (one record), got {x0.shape}.")
    if u.ndim != 2 or z.ndim != 2 or u.shape[0] != z.shape[0]:
        raise ValueError(
            f"`u` and `z` must have shapes (T, n_u) and (T, n_z) (one record), got {u.shape} "
            f"and {z.shape}."
        )
    if not np.all(np.isfinite(z)):
        raise ValueError("`z` has missing (NaN) or infinite samples; `fit_orthogonal` needs all.")
    # The checks of `fit` (z's columns against the model's outputs, u's and weight's values),
    # before the data are laid out for the augmented model.
    check_data(model, theta0, x0, u, z, weight, theta_name="theta0")
    names = _free_physics(theta0, keys, held)
    if not names:
        raise ValueError("`fixed` holds every physical parameter: nothing to keep orthogonal.")
    (T, n_u), n_x, n_z = u.shape, x0.shape[0], z.shape[1]
    w = np.eye(n_z) if weight is None else np.asarray(weight, dtype=float)
    w = np.diag(np.atleast_1d(w)) if w.ndim <= 1 else w  # (a scalar for one output)
    if w.shape != (n_z, n_z):
        raise ValueError(f"`weight` must have shape ({n_z},) or ({n_z}, {n_z}), got {w.shape}.")
    vals, vecs = np.linalg.eigh((w + w.T) / 2)
    root = vecs @ np.diag(np.sqrt(np.clip(vals, 0, None))) @ vecs.T  # W^{1/2}, symmetric

    # Python numbers as float arrays, so that the sensitivities see them as parameters
    # (`fit` estimates a Python int as it does a float).
    theta = jax.tree_util.tree_map(
        lambda a: np.asarray(a, float) if is_weak(a) else a, dict(theta0)
    )
    p = sum(
        np.size(a)
        for a in jax.tree_util.tree_leaves(
            eqx.filter({k: theta[k] for k in names}, eqx.is_inexact_array)
        )
    )
    aug = _augmented(model, keys, n_x, n_u, n_z, p)
    z_aug = np.concatenate([z, np.full((T, p), np.nan)], axis=1)
    z_aug[-1, n_z:] = 0.0  # the accumulated projection, read at the last sample, is 0
    w_aug = np.zeros((n_z + p, n_z + p))
    w_aug[:n_z, :n_z] = w
    w_aug[n_z:, n_z:] = strength * np.eye(p)
    est = np.asarray(estimate_x0)
    if est.dtype != bool or est.shape not in ((), (n_x,)):
        raise ValueError(
            f"`estimate_x0` must be a boolean or an ({n_x},) boolean mask, got {estimate_x0!r}."
        )
    est = np.broadcast_to(est, (n_x,))
    est_aug = np.concatenate([est, np.zeros(n_x + p, bool)])

    history, result, converged = [], None, False
    m = _basis(model, theta, x0, u, names, root)
    if not np.all(np.isfinite(m)):
        raise ValueError(
            f"the model's outputs or their sensitivities to the physical parameters {names} "
            "are not finite at theta0 and x0: start where the model simulates "
            "(`oneshot_jax.simulate(model, theta0, x0, u)` finite)."
        )
    with at_caller(__file__):  # (the rounds' warnings, at the caller's line)
        for _ in range(int(rounds)):
            before = _flat(theta, names)
            if not np.all(np.isfinite(m)):
                break  # not converged: the basis cannot be formed at this estimate
            u_aug = np.concatenate([u, m.reshape(T, n_z * p)], axis=1)
            x0_aug = np.concatenate([x0, np.zeros(n_x + p)])
            with warnings.catch_warnings():
                # (The augmented outputs are the penalty's rows, one sample each: `fit`'s
                # advice to weigh the outputs by their noise is not the user's to act on.)
                warnings.filterwarnings("ignore", "the weighted residuals of the outputs differ")
                result = fit(
                    aug,
                    theta,
                    x0_aug,
                    u_aug,
                    z_aug,
                    solver=solver,
                    weight=w_aug,
                    fixed=None if fixed is None else {k: held.get(k, False) for k in theta0},
                    estimate_x0=est_aug,
                    missing="mask",
                    **kwargs,
                )
            theta, x0 = result.theta, np.asarray(result.x0)[:n_x]
            after = _flat(theta, names)
            step = np.abs(after - before)
            change = float(np.max(step / np.maximum(np.abs(before), 1e-12)))
            std = _flat(result.std, names)
            held_entry = (std == 0) & (step == 0)  # (fixed: a leaf held in part)
            ok = np.isfinite(std) & (std > 0)
            moved = np.where(ok, step / np.where(ok, std, 1.0), np.inf)
            moved = float(np.max(np.where(held_entry, 0.0, moved), initial=0.0))
            _, y = simulate(model, theta, x0, u)
            _, y_off = simulate(model, _off(theta, keys), x0, u)
            d = (np.asarray(y) - np.asarray(y_off)) @ root
            # The basis at the new estimate (the next round's): the network moved in the
            # round, and with it the sensitivities. The round held Q fixed, so its own
            # projection, 3e-5, said nothing of the new Q's, 0.38 (a pendulum whose
            # network carried physics worth 3 standard errors of w0sq, "converged").
            sw = _sensitivities(model, theta, x0, u, names, root)
            m = _orthonormal(sw, root)
            along = np.einsum("tj,tjp->p", np.asarray(y) - np.asarray(y_off), m)
            norm = float(np.linalg.norm(d))
            absorbed, absorbed_change = _absorbed(sw, d.reshape(-1), std, after, ~held_entry)
            history.append(
                Round(
                    physics={k: theta[k] for k in names},
                    loss=float(loss(model, theta, x0, u, z, weight=weight)),
                    projection=float(np.linalg.norm(along)) / norm if norm > 0 else 0.0,
                    change=change,
                    moved=moved,
                    absorbed=absorbed,
                    status=result.status,
                )
            )
            # (only a round whose fit reached its optimum: one that stopped short, on its
            # step budget or with a network's units saturated and its gradient zero,
            # moves the physics little without having settled it; and only where the
            # network carries no physics worth `stol` standard errors at its end)
            settled = (moved <= stol or change <= rtol) and (
                absorbed <= stol or absorbed_change <= rtol
            )
            if result.success and settled:
                converged = True
                break
    return Orthogonal(
        theta=theta,
        x0=x0,
        loss=history[-1].loss,
        rounds=tuple(history),
        result=result,
        converged=converged,
    )
