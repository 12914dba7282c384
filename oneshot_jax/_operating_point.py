"""Operating points of a model: its equilibria at a constant input (MATLAB's `findop`
with `'steady'`) and the linear model of the deviations around one (MATLAB's
`linearize` of an `idnlgrey`).

An equilibrium at the input u is a state x with f(x, u, theta) = x, eq. (1) of the paper
at rest; for a model built from an ODE (`Model.from_ode`), rhs(x, u, theta) = 0, solved
on the right-hand side itself (the integrator's fixed points are its zeros, and its
residual is in the state's units per unit time, independent of dt). The linear model of
eq. (1)-(2) around (x, u) is the first-order expansion of f and g:

    dx[k+1] = A dx[k] + B du[k],   dz[k] = C dx[k] + D du[k],

A = df/dx, B = df/du, C = dg/dx, D = dg/du at (x, u) (A and C are the one-shot
recursion's J^{x/x} and J^{z/x} of eq. (12)-(13) at one sample; the input's B and D are
not in the paper), and for an ODE model also the continuous-time
Ac = d rhs / dx, Bc = d rhs / du.
"""

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, PyTree

from . import _pytree
from ._checks import as_float, check_data, check_finite
from ._counts import is_count
from ._linalg import psd_solve
from ._model import ODE_STEPS, Model


class Equilibrium(NamedTuple):
    """What `find_equilibrium` returns.

    - `x`: (n_x,) the state found.
    - `z`: (n_z,) the outputs there, g(x, u, theta).
    - `u`: (n_u,) the input.
    - `residual`: the largest |entry| of the equation's residual at `x`: of rhs(x, u,
        theta) for a model built from an ODE, else of f(x, u, theta) - x.
    - `success`: True where the residual is at the round-off level of the equation (each
        entry at most sqrt(eps) times its row's scale at `x`, sum_j |J_ij| max(|x_j|, 1):
        the size of its terms that depend on the state); False
        where no equilibrium was reached (none near the start, or none at this input:
        an integrator driven by a constant force).
    - `steps`: the Gauss-Newton steps taken.
    """

    x: np.ndarray
    z: np.ndarray
    u: np.ndarray
    residual: float
    success: bool
    steps: int

    @property
    def message(self) -> str:
        """Why the search stopped, in words."""
        if self.success:
            return (
                f"equilibrium: the residual is {self.residual:.3g}, at the round-off level "
                f"of the equation ({self.steps} Gauss-Newton steps)"
            )
        return (
            f"no equilibrium reached: the residual stays at {self.residual:.3g} after "
            f"{self.steps} Gauss-Newton steps (none near the start `x`, or none at this "
            "input); try another start"
        )

    def __str__(self) -> str:
        return f"Equilibrium(x={self.x}, z={self.z}): {self.message}"

    __repr__ = __str__


class LinearModel(NamedTuple):
    """What `linearise` returns: the linear model of the deviations around (x, u).

    - `A` (n_x, n_x), `B` (n_x, n_u), `C` (n_z, n_x), `D` (n_z, n_u): the discrete-time
        model dx[k+1] = A dx[k] + B du[k], dz[k] = C dx[k] + D du[k] of one sample
        interval (the Jacobians of `step` and `observe`). For `input="foh"`, whose step
        dx[k+1] = A dx[k] + B0 du[k] + B1 du[k+1] reads the next sample's input too, the
        model is that step's exact state-space form (MATLAB's `c2d(sys, dt, 'foh')`
        form): B = B0 + A B1 and D = D_g + C B1 (D_g the Jacobian of `observe`), for the
        state xi[k] = dx[k] - B1 du[k] (`B_next` is B1); its frequency response is the
        foh model's, C (z I - A)^{-1} (B0 + z B1) + D_g.
    - `Ac` (n_x, n_x), `Bc` (n_x, n_u): for a model built from an ODE, the
        continuous-time d(dx)/dt = Ac dx + Bc du (the Jacobians of `rhs`); None otherwise.
    - `dt`: the sample interval of A and B (None for a `Model(step)`, whose step has
        none).
    - `x`, `u`: the operating point.
    - `B_next` (n_x, n_u): for `input="foh"`, B1, the step's Jacobian with respect to
        the next sample's input (dx[k] = xi[k] + B1 du[k]); None otherwise.
    - `D_observe` (n_z, n_u): for `input="foh"`, D_g, the Jacobian of `observe` in u (the
        continuous-time model's feedthrough; `D` is D_g + C B1); None otherwise.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    Ac: np.ndarray | None
    Bc: np.ndarray | None
    dt: float | None
    x: np.ndarray
    u: np.ndarray
    B_next: np.ndarray | None = None
    D_observe: np.ndarray | None = None

    @property
    def poles(self) -> np.ndarray:
        """The eigenvalues of A: the discrete-time poles (stable inside the unit circle).
        The continuous-time ones of an ODE model are `np.linalg.eigvals(lin.Ac)`."""
        return np.linalg.eigvals(self.A)

    def dcgain(self, *, continuous=False) -> np.ndarray:
        """The steady-state gain (n_z, n_u) of the deviations (MATLAB's `dcgain`): the
        frequency response at w = 0, C (I - A)^{-1} B + D, or with `continuous=True`
        -C Ac^{-1} Bc + D of an ODE model's continuous-time one (the same up to the
        integrator's error). Infinite where the model integrates (a pole at 1, or at 0)."""
        return self.frequency_response(np.zeros(1), continuous=continuous)[0].real

    def step_response(self, n) -> np.ndarray:
        """The discrete-time response to a unit step of each input from rest (MATLAB's
        `step` of the sampled model): an array (n, n_z, n_u), entry [k, i, j] the
        deviation of output i at sample k after input j steps to 1 at sample 0 (the
        state at rest, dx[0] = 0: dz[0] = D). For `input="foh"` the step is the input's
        samples, interpolated between them as the model runs them."""
        if not is_count(n, 1):
            raise ValueError(
                f"`n` (the samples of the response) must be an integer >= 1, got {n!r}."
            )
        n_x, n_u = self.B.shape
        # (the state-space form's state xi = dx - B1 du: -B1 at rest with du = 1)
        xi = np.zeros((n_x, n_u)) if self.B_next is None else -np.asarray(self.B_next)
        out = np.empty((int(n), self.C.shape[0], n_u))
        for k in range(int(n)):
            out[k] = self.C @ xi + self.D
            xi = self.A @ xi + self.B
        return out

    def frequency_response(self, w, *, continuous=False) -> np.ndarray:
        """The frequency response H (n_w, n_z, n_u) at the angular frequencies `w` (n_w,)
        (MATLAB's `freqresp`, what `bode` plots): C (e^{j w dt} I - A)^{-1} B + D of the
        discrete-time model, w in radians per unit of `dt` (per sample where `dt` is
        None), or with `continuous=True` C (j w I - Ac)^{-1} Bc + D of an ODE model's
        continuous-time one. |H| is the gain, np.angle(H) the phase; at a frequency on a
        pole (an integrator's w = 0) H is infinite, as MATLAB's `freqresp` gives it."""
        w = frequencies(w)
        if not isinstance(continuous, (bool, np.bool_)):
            raise TypeError(f"`continuous` must be True or False, got {continuous!r}.")
        if continuous:
            if self.Ac is None:
                raise ValueError(
                    "`continuous=True` needs a model built from an ODE (`Model.from_ode`): "
                    "this linear model has no Ac, Bc."
                )
            # (the ODE's own feedthrough: a foh model's D holds C B1 of its sampling too)
            s, A, B = 1j * w, self.Ac, self.Bc
            D = self.D if self.D_observe is None else self.D_observe
        else:
            s, A, B = np.exp(1j * w * (1.0 if self.dt is None else self.dt)), self.A, self.B
            D = self.D
        eye = np.eye(A.shape[0])
        M = s[:, None, None] * eye - A
        try:
            X = np.linalg.solve(M, np.broadcast_to(B, (len(w), *B.shape)))
        except np.linalg.LinAlgError:  # (a frequency on a pole: H infinite there)
            X = np.empty((len(w), *B.shape), complex)
            for i in range(len(w)):
                try:
                    X[i] = np.linalg.solve(M[i], B)
                except np.linalg.LinAlgError:
                    X[i] = complex(np.inf, 0.0)
        with np.errstate(invalid="ignore"):
            H = self.C @ X + D
        return np.where(np.isfinite(X).all(axis=(1, 2))[:, None, None], H, complex(np.inf, 0.0))

    def __str__(self) -> str:
        kind = "" if self.Ac is None else ", with the continuous-time Ac, Bc"
        if self.B_next is not None:
            kind += "; foh: state xi = dx - B_next du"
        every = "" if self.dt is None else f" of dt = {self.dt:g}"
        n_x, n_u, n_z = self.A.shape[0], self.B.shape[1], self.C.shape[0]
        return (
            f"LinearModel{every}: {n_x} states, {n_u} inputs, {n_z} outputs{kind}; poles "
            f"{np.round(self.poles, 6)}"
        )

    __repr__ = __str__


def frequencies(w, positive=False):
    """Angular frequencies as a 1-D float64 array of finite real numbers (positive ones
    for a log axis where `positive`)."""
    if np.asarray(w).dtype == bool:
        raise TypeError(f"`w` must hold angular frequencies (real numbers), got {w!r}.")
    a = np.asarray(as_float(w, "w"), np.float64)
    if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError(
            f"`w` must be a non-empty 1-D array of finite angular frequencies, got {w!r}."
        )
    if positive and np.any(a <= 0):
        raise ValueError(
            f"`w` must hold positive angular frequencies (the Bode plot's axis is "
            f"logarithmic), got {np.min(a):g} among them."
        )
    return a


def _model(model):
    if not isinstance(model, Model):
        raise TypeError(f"`model` must be a oneshot_jax.Model, got {type(model).__name__}.")


def _input(u):
    """The constant input as an (n_u,) floating array."""
    a = as_float(u, "u")
    if a.ndim != 1:
        raise ValueError(
            f"`u` must be the constant input, shape (n_u,) ((0,) for a model without "
            f"inputs), got shape {a.shape}."
        )
    return np.asarray(a)


def _checked(model, theta, x, u, dt, call):
    """`check_data` of the operating point as a record of two equal samples (the step
    sees u held over an interval `dt` for a model of time-stamped records). A state or
    an input that does not fit the model is refused naming `x` and `u` and the order
    `call` takes them in (`linearise` and `find_equilibrium` differ: a swap is the likely
    cause; check_data's own words speak of a record's x0 and u)."""
    u = _input(u)
    if isinstance(x, Equilibrium):
        raise TypeError("`x` is an Equilibrium: pass its state, `eq.x` (and its input `eq.u`).")
    if np.ndim(x) != 1:
        raise ValueError(f"`x` must be one state, shape (n_x,), got shape {np.shape(x)}.")
    x = as_float(x, "x")
    check_finite(x, "x")
    check_finite(u, "u")
    t = None if not model.timed else np.array([0.0, dt])
    try:
        data = check_data(model, theta, x, np.stack([u, u]), t=t)
    except ValueError as err:
        # (a swap is named only where the swapped pair fits the model)
        swapped = np.shape(x) != np.shape(u) and _fits(model, theta, u, x, t)
        question = (
            f" (`{call}`: are they swapped? they fit it the other way round)" if swapped else ""
        )
        raise ValueError(
            f"`x` (shape {np.shape(x)}) and `u` (shape {np.shape(u)}) do not fit the model"
            f"{question}; as a record's x0 and u (two samples of u): {err}"
        ) from None
    return data, u


def _fits(model, theta, x, u, t) -> bool:
    """Whether the state `x` and the input `u` pass `check_data` for `model`."""
    try:
        check_data(model, theta, x, np.stack([u, u]), t=t)
    except (ValueError, TypeError):
        return False
    return True


def _interval(model, dt, need):
    """The sample interval of a timed model's step (`dt`, given), checked; None for a
    model of a fixed interval, which refuses one, and for a timed model where it is not
    `need`ed and not given."""
    if not model.timed:
        if dt is not None:
            raise ValueError(
                "`dt` is for a model of time-stamped records (`Model.from_ode(rhs, "
                "dt=None)`); this model's step has its own interval."
            )
        return None
    if dt is None:
        if not need:
            return None
        raise ValueError(
            "`dt` (the sample interval of the step) is needed for a model of time-stamped "
            "records (`Model.from_ode(rhs, dt=None)`, or `Model(step, timed=True)`)."
        )
    if hasattr(dt, "item") and np.shape(dt) == ():
        dt = dt.item()  # (a 0-d array)
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating, np.integer)):
        raise TypeError(f"`dt` must be a positive number, got {dt!r}.")
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"`dt` must be a finite positive number, got {dt!r}.")
    return float(dt)


def _rhs(model):
    return model.step.rhs if isinstance(model.step, ODE_STEPS) else None


@eqx.filter_jit
def _equation(model, rhs, theta, x, su, u):
    """The residual of the equilibrium's equation at x and its Jacobian in x: rhs(x, u,
    theta) for an ODE model (`rhs` given, theta whole), else f(x, su, theta) - x (the
    bound model, theta's parameters)."""

    def residual(x):
        if rhs is not None:
            return rhs(x, u, theta)
        return model.step(x, su, theta) - x

    return residual(x), jax.jacfwd(residual)(x)


# At most this many Gauss-Newton steps, and halvings of one (`find_equilibrium`).
MAX_STEPS = 100
HALVINGS = 30


def find_equilibrium(
    model,
    theta: PyTree,
    u: Float[ArrayLike, " n_u"],
    x: Float[ArrayLike, " n_x"],
    *,
    hold=None,
    dt=None,
) -> Equilibrium | list[Equilibrium]:
    """An equilibrium of the model at a constant input (MATLAB's `findop(sys, 'steady',
    u)`): a state x with f(x, u, theta) = x, or rhs(x, u, theta) = 0 for a model built
    from an ODE (the module's docstring).

    Gauss-Newton from the start `x` on the residual of that equation, its step the
    pseudo-inverse's (a direction along which every state is an equilibrium, a position
    that no force depends on, keeps its start), each step halved until it lowers the
    residual's norm.

    **Arguments:**

    - `model`, `theta`: a `Model` and its parameters.
    - `u`: the constant input (n_u,); or a sweep of N inputs (N, n_u) (the static
        characteristic: the equilibria along an input's range), each searched from the
        equilibrium of the row before (continuation along the sweep), from `x` for the
        first row and after a row without one.
    - `x`: the start of the search (n_x,), e.g. the fitted x0.
    - `hold`: None, or an (n_x,) boolean mask of the entries of `x` held at their given
        values (MATLAB's known states of `findop`); the others are solved for, in the
        least-squares sense of all the equations.
    - `dt`: only for a model of time-stamped records whose step is not built from an ODE
        (`Model(step, timed=True)`): the sample interval whose step's fixed points are
        sought (they depend on it; an ODE's zeros of rhs do not, and need none).

    **Returns:** an `Equilibrium` (`x`, `z`, `u`, `residual`, `success`, `steps`);
    `success` False, with the residual it reached, where none was found. For a sweep, a
    list of N.

    **Raises:** `ValueError` for `u` or `x` of the wrong shape (or a state the model does
    not take), a `hold` that is not an (n_x,) boolean mask; `TypeError` for a `model`
    that is not a `Model`.
    """
    _model(model)
    u = as_float(u, "u")
    if np.ndim(u) > 2:
        raise ValueError(
            f"`u` must be the constant input (n_u,) or a sweep of N inputs (N, n_u), got "
            f"shape {np.shape(u)}."
        )
    if np.ndim(u) == 2:  # a sweep, continued from row to row
        out, start = [], x
        for row in np.asarray(u):
            eq = find_equilibrium(model, theta, row, start, hold=hold, dt=dt)
            out.append(eq)
            start = eq.x if eq.success else x
        return out
    # (an ODE's zeros of rhs do not depend on the interval: any will do)
    dt = _interval(model, dt, need=_rhs(model) is None)
    if dt is None and model.timed:
        dt = 1.0
    data, u = _checked(model, theta, x, u, dt, "find_equilibrium(model, theta, u, x)")
    n_x = data.x0.shape[0]
    free = np.ones(n_x, bool)
    if hold is not None:
        mask = np.asarray(hold)
        if mask.dtype != bool or mask.shape != (n_x,):
            raise ValueError(
                f"`hold` must be an (n_x,) = ({n_x},) boolean mask, True for the entries of "
                f"`x` held at their values, got {hold!r}."
            )
        free = ~mask
    rhs = _rhs(model)
    whole = _pytree.combine(data.theta, data.static)
    su = data.model.step_inputs(jnp.asarray(data.u))[0]
    ue = jnp.asarray(u, data.x0.dtype)
    params = whole if rhs is not None else data.theta

    def evaluate(x):
        """The residual and its Jacobian in all the entries (for `scale`: a held entry's
        terms are the equation's too; the step takes the free entries' columns)."""
        r, J = _equation(data.model, rhs, params, jnp.asarray(x, data.x0.dtype), su, ue)
        return np.asarray(r, np.float64), np.asarray(J, np.float64)

    x = np.asarray(data.x0, np.float64)
    r, J_all = evaluate(x)
    eps = float(np.finfo(data.x0.dtype).eps)

    def scale(x, J):
        # The equation's at x: the size of its terms that depend on the state, |J| |x|
        # (the round-off of a residual whose terms cancel). Not the residual at the start:
        # a far start made it loose, and a point that was no equilibrium passed (u - (x -
        # 1000)^2 = 0 at u = -1e-3 has none; from x = 0, residual 1e6 there, the least-
        # squares point, residual 1e-3, read success).
        # Per equation (row): states in units of very different sizes (a level in m
        # next to a pressure in Pa) made one scale for all of them 1e9 times a level's,
        # and a tank that overflowed at 1 m/s read as an equilibrium.
        return np.abs(J) @ np.maximum(np.abs(x), 1.0)

    steps = 0
    while (
        steps < MAX_STEPS
        and np.all(np.isfinite(r))
        and np.any(np.abs(r) > eps * scale(x, J_all))  # (at round-off: stop)
    ):
        J = J_all * free[None, :]
        step = -np.asarray(psd_solve(jnp.asarray(J.T @ J), jnp.asarray(J.T @ r)))
        now, alpha = r @ r, 1.0
        for _ in range(HALVINGS):
            trial = (x + alpha * step).astype(data.x0.dtype)
            r_t, J_all_t = evaluate(trial)
            if np.all(np.isfinite(r_t)) and r_t @ r_t < now:
                break
            alpha *= 0.5
        else:  # (no step lowers the residual: its round-off floor, or its least-squares
            break  # minimum where there is no equilibrium)
        x, r, J_all = np.asarray(trial, np.float64), r_t, J_all_t
        steps += 1
    residual = float(np.max(np.abs(r), initial=0.0))
    success = bool(np.all(np.isfinite(r)) and np.all(np.abs(r) <= math.sqrt(eps) * scale(x, J_all)))
    x = x.astype(data.x0.dtype)
    z = data.model.observe(jnp.asarray(x), jnp.asarray(data.u[0]), data.theta)
    return Equilibrium(x, np.asarray(z), u, residual, success, steps)


@eqx.filter_jit
def _jacobians(model, rhs, params, whole, x, su, uo, u):
    """A, B, C, D (the interval column left out), for an ODE model Ac, Bc, and for a
    "foh" pair B1 and D_g, the observation's own: B and D then those of its state-space
    form (`LinearModel`), B0 + A B1 and D_g + C B1."""
    n_u = u.shape[0]
    A, Bs = jax.jacfwd(model.step, (0, 1))(x, su, params)  # Bs: (n_x, [2,] n_u [+ 1])
    C, D = jax.jacfwd(model.observe, (0, 1))(x, uo, params)
    D, B1, D_g = D[:, :n_u], None, None
    if su.ndim == 2:  # (u[k] and u[k+1])
        B0, B1, D_g = Bs[:, 0, :n_u], Bs[:, 1, :n_u], D
        B, D = B0 + A @ B1, D + C @ B1
    else:
        B = Bs[:, :n_u]
    if rhs is None:
        return A, B, C, D, None, None, B1, D_g
    return A, B, C, D, *jax.jacfwd(rhs, (0, 1))(x, u, whole), B1, D_g


def linearise(
    model,
    theta: PyTree,
    x: Float[ArrayLike, " n_x"],
    u: Float[ArrayLike, " n_u"],
    *,
    dt=None,
) -> LinearModel:
    """The linear model of the deviations around the operating point (x, u) (MATLAB's
    `linearize(sys, u0, x0)` of an `idnlgrey`): the Jacobians of the model's step and
    observation there (the module's docstring), by forward-mode differentiation.

    The point need not be an equilibrium (`find_equilibrium` finds one); away from one,
    the expansion is that of one step from x, and dx[k] stays small only while the
    trajectory stays near x.

    **Arguments:**

    - `model`, `theta`: a `Model` and its parameters.
    - `x`: the state (n_x,); `u`: the input (n_u,) of the operating point.
    - `dt`: only for a model of time-stamped records (`Model.from_ode(rhs, dt=None)`):
        the sample interval of A and B.

    **Returns:** a `LinearModel` (`A`, `B`, `C`, `D`; `Ac`, `Bc` for an ODE model; `dt`,
    `x`, `u`; `poles`).

    **Raises:** `ValueError` for arrays of the wrong shape, a missing or needless `dt`;
    `TypeError` for a `model` that is not a `Model`.
    """
    _model(model)
    interval = _interval(model, dt, need=True)
    data, u = _checked(model, theta, x, u, interval, "linearise(model, theta, x, u)")
    rhs = _rhs(model)
    whole = _pytree.combine(data.theta, data.static)
    U = jnp.asarray(data.u)
    x = jnp.asarray(data.x0)
    out = _jacobians(
        data.model,
        rhs,
        data.theta,
        whole,
        x,
        data.model.step_inputs(U)[0],
        U[0],
        jnp.asarray(u, x.dtype),
    )
    A, B, C, D, Ac, Bc, B1, D_g = (None if a is None else np.asarray(a) for a in out)
    step_dt = getattr(model.step, "dt", None) if interval is None else interval
    point = (np.asarray(x), np.asarray(u, x.dtype))
    return LinearModel(A, B, C, D, Ac, Bc, step_dt, *point, B1, D_g)
