"""Levenberg-Marquardt: the linearisation's damped step (`_linearisation`) with Nielsen's
damping update (`_search.NielsenDamping`) in the loop of `least_squares`."""

import equinox as eqx

from .._counts import integral, real
from ._search import NielsenDamping
from .base import check_options
from .least_squares import AbstractLeastSquares


class LevenbergMarquardt(AbstractLeastSquares):
    """Levenberg-Marquardt on the closed-form residual Jacobian (forward sensitivities),
    with Marquardt's scaling D = diag(J^T J), the x0 blocks of each trajectory eliminated
    by a Schur complement and an exact active set for box bounds. A step that fails (one
    that a bound or a projection clipped can predict no decrease at any damping) is
    followed by a projected-gradient step with an Armijo search along the projection arc
    (Kanzow, Yamashita and Fukushima 2004). The damping mu follows Nielsen's rule: on an
    accepted step mu *= max(1/3, 1 - (2 rho - 1)^3), on a rejected one mu *= nu,
    nu *= 2 (rho = actual / predicted decrease). A non-finite trial loss is a rejected
    step.

    **Arguments:**

    - `gtol`: the first-order test: the fit converges (succeeds) when the scaled
        projected gradient, the largest cosine between the residual and a Jacobian
        column, is at most `gtol` (see `oneshot_jax._optimality`).
    - `stol`: the statistical test, only where theta's columns of the Jacobian have a
        null space once the initial states are fitted (a network in theta): the fit
        converges (succeeds, `statistically_converged`) when an accepted step moves it by
        at most `stol` standard errors, with the conditions given under `GaussNewton`
        (and, on a regular Jacobian, settles a stop at round-off as described there).
        0 turns it off.
    - `rtol`, `atol`: an optional step test (off by default): an accepted step of
        scaled size at most rtol ||D p|| + atol that decreased the loss by at most
        rtol C + atol ends the fit, as `converged` if the first-order measure is at
        most gtol there, or at most its round-off limit (10 sqrt(eps), raised where the
        outputs are far above the residuals: `_optimality.stall_limit`), and as `stalled`
        otherwise (see `oneshot_jax._solver.least_squares`). Without it
        the fit runs until the first-order test holds, no step can decrease the loss at
        round-off, or `max_steps`.
    - `max_steps`: the maximum number of iterations (rejected steps count).
    - `mu0`: the initial damping.
    - `strategy`: how the sensitivities are computed (`"auto"`, `"jacobian"`, `"vjp"`,
        `"parallel"`; see `GaussNewton`).
    - `linear_solver`: how the normal equations are solved: `"dense"` (the Jacobian
        formed, one forward-sensitivity column per free parameter), `"cg"` (matrix-free:
        conjugate gradients on Jacobian-vector products, for a large theta such as a
        neural residual) or `"auto"` (`"cg"` above 256 free entries of theta, except
        with `strategy="parallel"`, whose sensitivities form the Jacobian; see
        `oneshot_jax._solver.least_squares`).
    - `cg_rtol`, `cg_max_steps`: the conjugate-gradient solve's relative residual and
        iteration budget per step (with `"cg"`).
    """

    TRACED_OPTIONS = AbstractLeastSquares.TRACED_OPTIONS + ("mu0",)

    rtol: float = eqx.field(default=0.0, converter=real)
    atol: float = eqx.field(default=0.0, converter=real)
    gtol: float = eqx.field(default=1e-8, converter=real)
    stol: float = eqx.field(default=1e-2, converter=real)
    max_steps: int = eqx.field(default=100, converter=integral)
    mu0: float = eqx.field(default=1e-3, converter=real)
    strategy: str = "auto"
    linear_solver: str = "auto"
    cg_rtol: float = eqx.field(default=1e-8, converter=real)
    cg_max_steps: int = eqx.field(default=50, converter=integral)

    def __check_init__(self):
        check_options(self, positive=("mu0",))
        self._check()

    def _search(self):
        return NielsenDamping(self.mu0)
