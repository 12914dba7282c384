r"""Standard errors of quantities derived from the parameters: the estimate's covariance
carried through a function of theta to first order (the delta method).

For q = h(theta) (a natural frequency sqrt(k / m), a time constant, a pole of the
linearised model) with J = dh / d theta over theta's free entries (forward-mode
differentiation of h) and Sigma their covariance (`FitResult.covariance`: sigma^2
(J^T J)^+ of the residuals of eq. (4)-(5), or its Newey-West sandwich,
`oneshot_jax._covariance`; theta's block, the initial states marginalised):

    Cov q = J Sigma J^T,

the first-order approximation, exact for an h linear in theta. Where Sigma is not
finite in an entry that q takes (J_i Sigma_ij J_j with J_i, J_j nonzero: a parameter
the data do not determine, a network's weights, a covariance not computed), q's standard
error is inf; a q of a hybrid's physical parameters alone takes their block of Sigma,
which is finite, and none of its covariances with the network's weights.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _pytree
from ._covariance import carried_covariance


class Derived(NamedTuple):
    """What `FitResult.delta_method` returns.

    - `value`: h(theta) at the estimate, an array of h's shape.
    - `std`: its standard errors, of the same shape (inf where not known).
    - `covariance`: (m, m) the covariance of h's m entries, flattened in C order (inf in
        the rows and columns of an entry whose std is inf).
    """

    value: np.ndarray
    std: np.ndarray
    covariance: np.ndarray

    @property
    def ci95(self):
        """95 % intervals value -+ 1.96 std, as (lower, upper)."""
        return self.value - 1.96 * self.std, self.value + 1.96 * self.std

    def __str__(self) -> str:
        rows = [
            f"{v:.6g} (std {s:.3g})"
            for v, s in zip(np.ravel(self.value), np.ravel(self.std), strict=True)
        ]
        return "Derived: " + ", ".join(rows[:8]) + (" ..." if len(rows) > 8 else "")

    __repr__ = __str__


def delta_method(fn, theta, fixed, covariance, name="fn"):
    """`Derived` of q = fn(theta) (the module's docstring): `theta` the estimate (any
    pytree), `fixed` the flat mask of its held entries, `covariance` Sigma over the free
    ones (another shape: not computed, every std inf)."""
    if not callable(fn):
        raise TypeError(f"`{name}` must be a function of theta, got {type(fn).__name__}.")
    params, static = _pytree.split(theta)
    flat, unravel = _pytree.ravel(params)
    free = np.flatnonzero(~np.asarray(fixed, bool))
    base = jnp.asarray(flat)

    def of(p):
        whole = _pytree.combine(unravel(base.at[free].set(p)), static)
        try:
            out = fn(_pytree.ordered_like(whole, theta))
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
            raise TypeError(
                f"`{name}` must be written in jax.numpy (it is differentiated by "
                "jax.jacfwd: NumPy functions, float(), Python branches on theta's values, "
                "and oneshot_jax.linearise and find_equilibrium, which return NumPy arrays, "
                "cannot follow it; write a Jacobian as jax.jacfwd(rhs)(x, u, theta))."
            ) from None
        except Exception as err:  # noqa: BLE001 - re-raised naming the call
            raise ValueError(
                f"calling `{name}(theta)` failed: {type(err).__name__}: {err}"
            ) from err
        try:
            q = jnp.asarray(out)
        except (TypeError, ValueError):
            raise TypeError(
                f"`{name}` must return real floating values (an array or a number), got "
                f"{type(out).__name__}: stack several quantities with jnp.stack."
            ) from None
        if jnp.iscomplexobj(q) or not jnp.issubdtype(q.dtype, jnp.floating):
            hint = (
                "for a complex quantity (a pole), return its jnp.real and jnp.imag, or "
                "jnp.abs and jnp.angle"
                if jnp.iscomplexobj(q)
                else "integers and booleans have no derivative in theta (a value that does "
                "not depend on theta, or a comparison); return a floating quantity computed "
                "from theta"
            )
            raise TypeError(
                f"`{name}` must return real floating values (an array or a number), got "
                f"dtype {q.dtype}: {hint}."
            )
        return q

    p = base[free]
    value = np.asarray(of(p), np.float64)
    if not np.all(np.isfinite(value)):
        raise ValueError(
            f"`{name}(theta)` is not finite at the estimate ({value!r}): its standard error "
            "would mean nothing there."
        )
    J = np.asarray(jax.jacfwd(of)(p), np.float64).reshape(value.size, free.size)
    # (an entry of Cov q is unknown where it takes an unknown entry of Sigma: a
    # hybrid's physical block is known, its covariances with the network's weights not)
    cov = carried_covariance(J, covariance, free.size)
    unknown = np.isinf(np.diag(cov))
    cov[unknown, :] = np.inf
    cov[:, unknown] = np.inf
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    return Derived(value, std.reshape(value.shape), 0.5 * (cov + cov.T))
