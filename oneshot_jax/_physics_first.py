r"""Hybrid fits whose physics stays identifiable: the physics first, then the network.

A learned term that sees more than the effect it stands for (a network fed the whole
state, r(q, q'), where the missing effect is a damping) can explain part of what the
physical parameters explain: a term in q trades with w0sq sin q, the data cannot tell
them apart, and a joint fit of eq. (5) leaves the physical parameters wherever the
solver's path ends. Gyorok et al. ("Orthogonal-by-construction augmentation of
physics-based input-output models", arXiv 2511.01321, 2025) remove the learned term's
component along the output sensitivities S = d yhat / d theta_phys: for an output
y = y_p(theta_phys) + P Delta(eta), P the projector onto the orthogonal complement of
S's columns (held fixed within a step), the normal equations of theta_phys read
S^T (y - y_p - P Delta) = S^T (y - y_p) = 0, those of the physical model alone. The
physical estimate is therefore the physics-only one, and the learned term explains only
what the physics cannot.

`fit_physics_first` reaches that estimate exactly, for any place of the learned term in
the model (inside the dynamics too), by two fits of eq. (5): the physical model alone
(every learned term switched off and held), then the learned terms with the physical
parameters held at that estimate. The second stage cannot move them, and it starts
from the first stage's loss, so it only lowers it.
"""

from collections.abc import Mapping

import equinox as eqx
import jax
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from ._fit import fit
from ._fit_result import FitResult


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
        return f"Physics first, then the learned terms:\n{head}\n{rows}\n\n{self.result}"

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
        if not any(eqx.is_inexact_array(a) for a in jax.tree_util.tree_leaves(theta0[k])):
            raise ValueError(f"`learned` names {k!r}, which holds no floating array to fit.")
    physical = [k for k in theta0 if k not in keys]
    if not any(
        eqx.is_inexact_array(a) or isinstance(a, float)
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
    `Dictionary`, whose output is linear in the last layer or the coefficients)."""
    return jax.tree_util.tree_map(
        lambda a: np.zeros_like(a) if eqx.is_inexact_array(a) else a, term
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
    terms see (a network fed the whole state cannot absorb part of the restoring force),
    and stage 2 only lowers the loss. This is the estimate of the
    orthogonal-by-construction augmentation of Gyorok et al. (arXiv 2511.01321, 2025),
    whose projection of the learned output off the physical output sensitivities leaves
    the physical normal equations S^T (y - y_p(theta_phys)) = 0 of the physics alone;
    here it holds for a learned term inside the dynamics too, and no projection is
    computed. The price: the physics is estimated with the unmodelled effect in its
    residuals (the physical model's own bias), which the joint fit would spread over
    both parts.

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
    keys, _ = _learned_keys(theta0, learned)
    held = _fixed(theta0, fixed)
    theta_phys = {k: (_switched_off(theta0[k]) if k in keys else theta0[k]) for k in theta0}
    if multistart is not False and isinstance(multistart, Mapping):
        wrong = [k for k in multistart if k in keys]
        if wrong:
            raise ValueError(
                f"`multistart` has starts of the learned terms {wrong!r}: stage 1 holds them."
            )
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
