"""Held-out data scored inside a fit's loop: the validation curve, the best iterate and
early stopping.

`fit(validation=Validation(u, z, n=...))` scores every iterate of every solver on records
the fit does not see: each record's initial state is estimated from its first n outputs
(Gauss-Newton on the head, from the last iterate's estimate and from the starting guess,
the lower head error kept), the model is
simulated from it over the whole record, and the score is the loss of eq. (4)/(5) with
the fit's weight Q over the samples after the head (the benchmark protocol's test error,
squared). The loop keeps the iterate with the lowest score (`oneshot_jax._iterate`), so
a run is never split into blocks (Adam's moments are not reset), and stops a solver after
`patience` scores without improvement.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._caller_warnings import warn
from ._checks import check_data, check_state_size
from ._cost import weigh
from ._counts import integral, is_count
from ._linalg import psd_solve
from ._normalise import is_ragged
from ._pytree import leaf_dtype
from ._simulate import outputs, rollout


class Validation(eqx.Module):
    """Held-out records that `fit` scores at every iterate (validation and early stopping).

    **Arguments:**

    - `u`, `z`: inputs and measured outputs of the held-out records, shaped like `fit`'s
        (T, n_u) and (T, n_z), or (N, T, .) for N records (of one length; no NaN).
    - `n`: the head: each record's initial state is estimated from its first `n` outputs
        (least squares, as `estimate_x0`), and the score counts the samples from n on
        (the benchmark protocol). None: the initial states are known, given as `x0`, and
        every sample counts.
    - `x0`: the records' initial states (n_x,) or (N, n_x): known ones with `n=None`,
        otherwise the starting guess of their estimate (default zeros). The estimates
        stay within the fit's `x0_bounds` where every fitted record has the same ones
        (as `FitResult.predict` keeps them).
    - `patience`: None (run each solver to its own stop), or stop a solver once its
        score has not improved for this many iterations (early stopping).
    - `x0_steps`: Gauss-Newton steps of each head estimate per iterate, at least 1 (with
        `n=None` it is not used). Each iterate runs them twice, from the previous
        iterate's estimate and from the starting guess `x0`, and keeps the estimate of
        the lower head error (the previous one alone can stay in another local minimum
        as theta moves).
    - `t`: the records' sample times, for a model of time-stamped records
        (`Model.from_ode(rhs, dt=None)`), as `fit`'s `t`.

    The fit returns the iterate with the lowest score over all its solvers, or the one
    the last solver stopped at with a success where its score ties with the lowest:
    above it by less than the score's own standard deviation (score sqrt(2 / n), n the
    samples scored times the outputs; a difference that the held-out records do not
    resolve). A stop that is not a success (the step budget, `patience`, a stall)
    returns the lowest-scored iterate.
    Where the returned iterate is not the one a solver stopped at, its stop reason is
    `RESULTS.validation` (not a success: the point is not a stationary point of the
    training loss). `FitResult.history.validation` holds the score of each recorded row
    and `FitResult.validation_loss` that of the returned iterate.
    """

    u: Any
    z: Any
    n: int | None = eqx.field(static=True, default=None, converter=integral)
    x0: Any = None
    patience: int | None = eqx.field(static=True, default=None, converter=integral)
    x0_steps: int = eqx.field(static=True, default=5, converter=integral)
    t: Any = None

    def __check_init__(self):
        if self.z is None:
            raise ValueError("`Validation` needs `z`, the held-out records' measured outputs.")
        try:
            z = np.asarray(self.z, dtype=float)
        except (TypeError, ValueError):  # (not numbers, ragged: `fit` names it)
            z = None
        if z is not None and np.isnan(z).any():
            raise ValueError(
                "`Validation`: `z` holds NaN: held-out records must be fully measured (score "
                "a record without its missing samples)."
            )
        if self.n is not None and not is_count(self.n, 1):
            raise ValueError(
                f"`Validation(n=...)` must be None or an integer >= 1, got {self.n!r}."
            )
        if self.n is None and self.x0 is None:
            raise ValueError(
                "`Validation` needs the records' initial states: `x0` (known), or `n` (the "
                "number of samples at the head to estimate them from)."
            )
        if self.patience is not None and not is_count(self.patience, 1):
            raise ValueError(
                "`Validation(patience=...)` must be None or an integer >= 1, got "
                f"{self.patience!r}."
            )
        if not is_count(self.x0_steps, 0):
            raise ValueError(
                f"`Validation(x0_steps=...)` must be an integer >= 0, got {self.x0_steps!r}."
            )
        if self.n is not None and self.x0_steps == 0:
            raise ValueError(
                "`Validation(x0_steps=0)` with `n` never estimates the initial states from "
                "the head: every iterate would be scored from the guess `x0`. Give "
                "x0_steps >= 1, or the known initial states as `x0` with n=None."
            )


# The head's Gauss-Newton step is halved at most this many times (`Monitor._head_x0`).
HALVINGS = 10

# Two validation scores tie where they differ by less than this fraction of the score's
# own standard deviation (`Monitor.tie`). (At 1 % of it, a
# Levenberg-Marquardt fit of a right model validated on records of the same system
# returned the iterate before its last step, not a success, in 4 of 8 noise draws, for
# differences of 0.14 to 0.40 standard deviations.)
TIE = 1.0


class Monitor(eqx.Module):
    """A `Validation` checked against the fit's model and data (built by `fit`): the
    records as (N, T, .) arrays, the head and the weight."""

    u: jax.Array  # (N, T, n_u)
    z: jax.Array  # (N, T, n_z)
    x0: jax.Array  # (N, n_x): known, or the starting guess
    sqrt_q: Any  # Q^{1/2} of the fit, or None
    n: int | None = eqx.field(static=True)
    patience: int | None = eqx.field(static=True)
    x0_steps: int = eqx.field(static=True)
    # The fit's `x0_bounds` (n_x,) each (-inf / inf unbounded) for the estimates from the
    # head, or None.
    x0_lower: Any = None
    x0_upper: Any = None

    def _clip(self, x):
        if self.x0_lower is None:
            return x
        return jnp.clip(x, self.x0_lower, self.x0_upper)

    def _head_x0(self, model, theta, x0, u, z):
        """Gauss-Newton on the head's weighted output error in x0 (pseudo-inverse for
        unobservable directions), each step halved until it lowers that error (at most
        `HALVINGS` times; the iterate stays where none does). A full step alone, kept
        only where it lowered the error, left a model nonlinear in x0 (an output
        x1^3 + x1) at a point that is no minimum, its score 0.6 % off.

        Within the fit's `x0_bounds`: an entry at a bound that the step pushes outwards
        is held there (its column of J left out) and the step solved again for the
        others, then the trial points are clipped into the box (a projected search
        path)."""
        n = self.n

        def residual(x):
            xs = rollout(model, theta, x, u[:n])
            return weigh(outputs(model, theta, xs, u[:n]) - z[:n], self.sqrt_q).ravel()

        def body(_, x):
            r = residual(x)
            J = jax.jacfwd(residual)(x)
            step = -psd_solve(J.T @ J, J.T @ r)
            if self.x0_lower is not None:  # (held at a bound it is pushed out of)
                held = ((x <= self.x0_lower) & (step < 0)) | ((x >= self.x0_upper) & (step > 0))
                Jf = jnp.where(held[None, :], 0.0, J)
                step = jnp.where(held, 0.0, -psd_solve(Jf.T @ Jf, Jf.T @ r))
            now = r @ r

            def lower(alpha):
                r_trial = residual(self._clip(x + alpha * step))
                return jnp.all(jnp.isfinite(r_trial)) & (r_trial @ r_trial < now)

            def halve(carry):
                alpha, k, _ = carry
                ok = lower(alpha)
                return jnp.where(ok, alpha, 0.5 * alpha), k + 1, ok

            alpha, _, ok = jax.lax.while_loop(
                lambda c: ~c[2] & (c[1] <= HALVINGS),
                halve,
                (jnp.ones((), x.dtype), jnp.array(0), jnp.array(False)),
            )
            return jnp.where(ok, self._clip(x + alpha * step), x)

        x = jax.lax.fori_loop(0, self.x0_steps, body, self._clip(x0))
        r = residual(x)
        return x, jnp.where(jnp.all(jnp.isfinite(r)), r @ r, jnp.inf)

    def score(self, model, theta, x0_guess):
        """The validation loss at `theta` (weighted mean squared output error over the
        samples after the head, every record) and the records' initial states used.

        Each record's x0 is estimated twice, from the last iterate's estimate (warm) and
        from the records' starting guess `x0`, and the one of the lower head error is kept:
        the warm start alone can stay in another local minimum of the head's error as
        theta moves (a hybrid's tank level, weakly observed, followed a minimum outside
        the range its network was trained on to 1e7, the score from 2e-3 to 80, where
        the guess's minimum, of half the head error, scored 1e-3)."""
        start = 0 if self.n is None else self.n

        def one(x0, guess, u, z):
            if self.n is not None:
                warm, e_warm = self._head_x0(model, theta, x0, u, z)
                cold, e_cold = self._head_x0(model, theta, guess, u, z)
                x0 = jnp.where(e_cold < e_warm, cold, warm)
            xs = rollout(model, theta, x0, u)
            e = weigh(outputs(model, theta, xs, u) - z, self.sqrt_q)[start:]
            return jnp.sum(e * e), x0

        sums, x0s = jax.vmap(one)(x0_guess, self.x0, self.u, self.z)
        count = self.u.shape[0] * (self.u.shape[1] - start)
        score = jnp.sum(sums) / count
        return jnp.where(jnp.isfinite(score), score, jnp.inf), x0s

    def tie(self, score):
        """The difference of scores below which two iterates tie on these records:
        `TIE` times the standard deviation of the score itself, score sqrt(2 / n) for n
        independent squared residuals of equal variance (the samples after the head
        times the outputs). A fit that converges with a score this close to the lowest
        returns its solution, not an iterate the records cannot tell apart from it."""
        start = 0 if self.n is None else self.n
        n = self.z.shape[0] * (self.z.shape[1] - start) * self.z.shape[2]
        return TIE * score * (2.0 / n) ** 0.5


def monitor(validation, model, theta, x0_fit, sqrt_q, n_u=None, x0_box=None):
    """The `Monitor` of `fit(validation=...)`: the records checked against the model like
    `fit`'s own data (errors name `validation`; `n_u` the fitted data's input columns),
    in the fit's dtype (that of `x0_fit`), or None. `x0_box`: the fit's `x0_bounds` as
    one (lower, upper) pair (n_x,) for the initial states estimated from the heads, or
    None."""
    if validation is None:
        return None
    if not isinstance(validation, Validation):
        raise TypeError(
            "`validation` must be an `oneshot_jax.Validation(u, z, n=...)` or None, got "
            f"{type(validation).__name__}."
        )
    u = validation.u
    if is_ragged(u) or is_ragged(validation.z):
        raise ValueError("`validation`: records of different lengths are not supported.")
    batched = np.ndim(u) == 3
    n_x = np.shape(x0_fit)[-1]
    x0 = validation.x0
    if x0 is not None:
        check_state_size(x0, n_x, "`validation`: `x0`")
    if x0 is None:
        x0 = np.zeros(
            (np.shape(u)[0], n_x) if batched else (n_x,),
            leaf_dtype(x0_fit),
        )
    try:
        shape = np.shape(u)
    except ValueError:  # (a list that is no array: `check_data` names it)
        shape = ()
    # (before the model's call; a timed model's checked inputs hold the intervals too,
    # compared after `check_data` below)
    if n_u is not None and not model.timed and len(shape) in (2, 3) and shape[-1] != n_u:
        raise ValueError(
            f"`validation`: `u` must have n_u = {n_u} input columns, as the fitted data "
            f"has; got shape {shape}."
        )
    try:
        data = check_data(model, theta, x0, u, validation.z, t=validation.t)
    except (ValueError, TypeError) as err:
        message = str(err)
        if "NaN or inf" in message:  # (the hint of `missing="mask"` is `fit`'s z's, not this)
            message = (
                message.split(" (")[0].rstrip(".") + ": held-out records must be fully measured."
            )
        elif "masked array" in message and "missing=" in message:  # (likewise)
            message = (
                message.split(", and its mask")[0]
                + ": held-out records must be fully measured (score a record without the "
                "masked samples)."
            )
        raise type(err)(f"`validation`: {message}") from None
    if data.lengths is not None:
        raise ValueError("`validation`: records of different lengths are not supported.")
    if n_u is not None and np.shape(data.u)[-1] != n_u:
        raise ValueError(
            f"`validation`: `u` must have n_u = {n_u} input columns, as the fitted data "
            f"has; got shape {np.shape(validation.u)}."
        )
    dtype = leaf_dtype(x0_fit)
    U, Z, X0 = (
        jnp.asarray(a, dtype) if data.batched else jnp.asarray(a, dtype)[None]
        for a in (data.u, data.z, data.x0)
    )
    T = U.shape[1]
    if validation.n is not None and validation.n >= T:
        raise ValueError(
            f"`Validation(n=...)` must be below the records' length {T}, got {validation.n}."
        )
    n_z = Z.shape[-1]
    if validation.n is not None and validation.n * n_z < n_x:
        warn(
            f"`Validation(n={validation.n})`: the head holds {validation.n * n_z} output "
            f"values, fewer than the {n_x} initial states estimated from it, so they are not "
            "determined by it (the estimate keeps its start along the others, and the score "
            f"depends on that start); a head of at least {-(-n_x // n_z)} samples, or more "
            "where the outputs show the state slowly.",
            stacklevel=4,
        )
    lower, upper = (None, None) if x0_box is None else (jnp.asarray(b, dtype) for b in x0_box)
    return Monitor(
        U, Z, X0, sqrt_q, validation.n, validation.patience, validation.x0_steps, lower, upper
    )
