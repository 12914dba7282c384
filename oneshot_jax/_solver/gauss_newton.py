"""Gauss-Newton: the linearisation's undamped step (`_linearisation`) with backtracking
(`_search.Backtracking`) in the loop of `least_squares`."""

import equinox as eqx

from .._counts import integral, real
from ._search import Backtracking
from .least_squares import AbstractLeastSquares


class GaussNewton(AbstractLeastSquares):
    """Gauss-Newton on the closed-form residual Jacobian (forward sensitivities), with the
    x0 blocks of each trajectory eliminated by a Schur complement, an exact active set for
    box bounds, and backtracking (alpha = 1, 1/2, ...) along the projection arc
    P(theta + alpha h) until the loss decreases; if it does not, a projected-gradient
    step with an Armijo search. A non-finite trial loss counts as no decrease.

    **Arguments:**

    - `gtol`: the first-order test: the fit converges (succeeds) when the scaled
        projected gradient, the largest cosine between the residual and a Jacobian
        column, is at most `gtol` (see `oneshot_jax._optimality`).
    - `stol`: the statistical test, only where theta's columns of the Jacobian have a
        null space once the initial states are fitted (an over-parameterised model such
        as a network, where the first-order test is not
        reached): the fit converges (succeeds, `statistically_converged`) when an
        accepted step, its predicted decrease of the loss confirmed by the actual one
        (at least a quarter of it), moves the fit by at most `stol` standard errors
        (predicted decrease at most stol^2 sigma^2, sigma^2 = C / (observations -
        rank J)), no parameter alone would move by a standard error (first-order
        measure at most 1 / sqrt(observations - rank J)), and the undamped Gauss-Newton
        step (the pseudo-inverse's, of the active set where there are bounds) is at most
        sqrt(rank J) standard errors (predicted decrease at most rank J sigma^2); see
        `oneshot_jax._optimality`. On a regular Jacobian it also settles a stop where no
        step lowers the loss at its round-off: `statistically_converged` where the
        undamped Gauss-Newton step from that point is at most `stol` standard errors and
        no parameter alone would move by one (`stop_info["settled"]`). 0 turns it off.
        Not tested with `linear_solver="cg"`, which does not form J^T J.
    - `rtol`, `atol`: an optional step test (off by default): an accepted step of
        scaled size at most rtol ||D p|| + atol that decreased the loss by at most
        rtol C + atol ends the fit, as `converged` if the first-order measure is at
        most gtol there, or at most its round-off limit (10 sqrt(eps), raised where the
        outputs are far above the residuals: `_optimality.stall_limit`), and as `stalled`
        otherwise (see `oneshot_jax._solver.least_squares`). Without it
        the fit runs until the first-order test holds, no step can decrease the loss at
        round-off, or `max_steps`.
    - `max_steps`: the maximum number of iterations.
    - `strategy`: how the sensitivities are computed (`"auto"`, `"jacobian"`: formed
        per-step Jacobians, `"vjp"`: matrix-free JVPs in the scan, `"parallel"`:
        associative scans; see `oneshot_jax._strategy`).
    - `linear_solver`: how the normal equations are solved: `"dense"` (the Jacobian
        formed, one forward-sensitivity column per free parameter), `"cg"` (matrix-free:
        conjugate gradients on Jacobian-vector products, for a large theta such as a
        neural residual) or `"auto"` (`"cg"` above 256 free entries of theta, except
        with `strategy="parallel"`, whose sensitivities form the Jacobian; see
        `oneshot_jax._solver.least_squares`).
    - `cg_rtol`, `cg_max_steps`: the conjugate-gradient solve's relative residual and
        iteration budget per step (with `"cg"`).
    """

    rtol: float = eqx.field(default=0.0, converter=real)
    atol: float = eqx.field(default=0.0, converter=real)
    gtol: float = eqx.field(default=1e-8, converter=real)
    stol: float = eqx.field(default=1e-2, converter=real)
    max_steps: int = eqx.field(default=100, converter=integral)
    strategy: str = "auto"
    linear_solver: str = "auto"
    cg_rtol: float = eqx.field(default=1e-8, converter=real)
    cg_max_steps: int = eqx.field(default=50, converter=integral)

    def __check_init__(self):
        self._check()

    def _search(self):
        return Backtracking()
