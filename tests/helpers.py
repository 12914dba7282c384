"""Shared test utilities: tree comparisons, independent oracles and the test problems.

Nothing here calls `oneshot_jax.loss` or the library's integrators: the oracles below
re-implement the rollout (a Python for-loop of our own classical RK4, or a diffrax
solver built from a Butcher tableau) and the cost of eq. (4), (5), (21) by hand, so that
`jax.grad` of them is an independent reference for the one-shot gradient.
"""

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

#
# Comparisons
#


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    """Same structure, shapes and dtypes, and elementwise close (the equinox helper)."""
    return eqx.tree_equal(x, y, typematch=True, rtol=rtol, atol=atol)


def tree_rel_errors(actual, expected):
    """Per leaf ||actual - expected|| / ||expected|| (inf where expected is zero but not actual)."""
    a_leaves, a_def = jax.tree_util.tree_flatten(actual)
    e_leaves, e_def = jax.tree_util.tree_flatten(expected)
    assert a_def == e_def, f"tree structures differ: {a_def} vs {e_def}"
    out = []
    for a, e in zip(a_leaves, e_leaves):
        a = np.asarray(a, dtype=np.float64)
        e = np.asarray(e, dtype=np.float64)
        diff, ref = np.linalg.norm(a - e), np.linalg.norm(e)
        out.append(diff / ref if ref > 0 else (0.0 if diff == 0 else np.inf))
    return out


def assert_tree_rel_close(actual, expected, *, rtol, atol=0.0, check_dtype=True):
    """Norm-wise relative check per leaf: ||a - b|| <= rtol ||b|| + atol.

    Also checks that both trees have the same structure and leaf shapes (and dtypes,
    unless `check_dtype=False`), so that a silently broadcast or mis-shaped gradient
    fails here rather than passing a loose numerical check.
    """
    a_leaves, a_def = jax.tree_util.tree_flatten(actual)
    e_leaves, e_def = jax.tree_util.tree_flatten(expected)
    assert a_def == e_def, f"tree structures differ: {a_def} vs {e_def}"
    for i, (a, e) in enumerate(zip(a_leaves, e_leaves)):
        assert jnp.shape(a) == jnp.shape(e), f"leaf {i}: shape {jnp.shape(a)} != {jnp.shape(e)}"
        if check_dtype:
            assert jnp.result_type(a) == jnp.result_type(e), (
                f"leaf {i}: dtype {jnp.result_type(a)} != {jnp.result_type(e)}"
            )
        a64 = np.asarray(a, dtype=np.float64)
        e64 = np.asarray(e, dtype=np.float64)
        assert np.all(np.isfinite(a64)), f"leaf {i}: non-finite values {a64}"
        diff, ref = np.linalg.norm(a64 - e64), np.linalg.norm(e64)
        assert diff <= rtol * ref + atol, (
            f"leaf {i}: ||a - b|| = {diff:.3e} > {rtol:.1e} * ||b|| ({ref:.3e}) + {atol:.1e}; "
            f"relative error {diff / ref if ref else np.inf:.3e}\na = {a64}\nb = {e64}"
        )


def benchmark_or_skip(loader, **kwargs):
    """`loader(**kwargs)` (a loader of `oneshot_jax.datasets`), or a skip naming the files
    it needs. The benchmark files are not part of the repository: they are found in
    `$ONESHOT_JAX_DATA` or `../shared/data` (hidden with `ONESHOT_JAX_HIDE_DATA=1`)."""
    try:
        return loader(**kwargs)
    except oj.datasets.DatasetNotFoundError as err:
        first = str(err).split(". ")[0]  # "<benchmark>: could not find <files>"
        pytest.skip(f"{first}: benchmark files, not in the repository (set ${oj.datasets.ENV_VAR})")


def fitted_order(hs, errors):
    """Least-squares slope of log(error) against log(h)."""
    return float(np.polyfit(np.log(np.asarray(hs)), np.log(np.asarray(errors)), 1)[0])


#
# Oracle A: our own classical RK4 in a Python for-loop, and the cost written by hand.
#


def own_rk4_step(rhs, x, u, theta, h):
    k1 = rhs(x, u, theta)
    k2 = rhs(x + (h / 2) * k1, u, theta)
    k3 = rhs(x + (h / 2) * k2, u, theta)
    k4 = rhs(x + h * k3, u, theta)
    return x + h * (k1 + 2 * k2 + 2 * k3 + k4) / 6


def own_euler_step(rhs, x, u, theta, h):
    return x + h * rhs(x, u, theta)


def own_step(rhs, dt, substeps=1, method="rk4"):
    """One sample interval of `rhs` under a zero-order hold, `substeps` steps of size dt/s.

    Jitted on its own so that a Python for-loop over k (see `loop_rollout`) stays cheap to
    differentiate: a fully unrolled, jitted rollout takes XLA minutes to compile.
    """
    one = own_rk4_step if method == "rk4" else own_euler_step

    @jax.jit
    def step(x, u, theta):
        h = dt / substeps
        for _ in range(substeps):
            x = one(rhs, x, u, theta, h)
        return x

    return step


def loop_rollout(step, theta, x0, u):
    """States x_0..x_{T-1} of eq. (7) as a Python list: x_{k+1} = step(x_k, u_k, theta)."""
    xs = [x0]
    for k in range(u.shape[0] - 1):
        xs.append(step(xs[-1], u[k], theta))
    return xs


def hand_cost(xs, theta, u, z, observe, weight, penalty, penalty_weight, *, loop=True):
    """C of eq. (4), (5), (21) for one trajectory, summed by hand over k:

    C = (1/T) sum_k [ e_k^T Q e_k + lambda h(x_k, theta) ],   e_k = g(x_k, u_k, theta) - z_k.

    `loop=True` is an explicit Python sum (for eager use); `loop=False` vmaps the same
    term over k (for use under `jax.jit`, where an unrolled loop compiles slowly).
    """

    def term(x, u_k, z_k, theta):
        e = observe(x, u_k, theta) - z_k
        if weight is None:
            out = jnp.dot(e, e)
        elif jnp.ndim(weight) == 1:
            out = jnp.dot(e, weight * e)
        else:
            out = jnp.dot(e, jnp.dot(weight, e))
        if penalty is not None:
            out = out + penalty_weight * penalty(x, theta)
        return out

    T = u.shape[0]
    if not loop:
        return jnp.sum(jax.vmap(term, in_axes=(0, 0, 0, None))(xs, u, z, theta)) / T
    term = jax.jit(term)
    total = 0.0
    for k in range(T):
        total = total + term(xs[k], u[k], z[k], theta)
    return total / T


def _identity(x, u, theta):
    del u, theta
    return x


#
# Oracle B: the same ODE integrated by diffrax, with classical RK4 given as a Butcher tableau.
#

_rk4_tableau = diffrax.ButcherTableau(
    a_lower=(np.array([1 / 2]), np.array([0.0, 1 / 2]), np.array([0.0, 0.0, 1.0])),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),
    c=np.array([1 / 2, 1 / 2, 1.0]),
)


class DiffraxRK4(diffrax.AbstractERK):
    """Classical 4th-order Runge--Kutta, defined through diffrax's ButcherTableau machinery."""

    tableau: ClassVar[diffrax.ButcherTableau] = _rk4_tableau

    @staticmethod
    def interpolation_cls(t0, t1, y0, y1, k):
        del k
        return diffrax.LocalLinearInterpolation(t0=t0, t1=t1, y0=y0, y1=y1)

    def order(self, terms):
        del terms
        return 4


def diffrax_rollout(rhs, dt, substeps, theta, x0, u, *, solver=None, controller=None):
    """States x_0..x_{T-1}: one `diffeqsolve` per sample interval with u_k held in `args`
    (zero-order hold), scanned over k.

    The vector field is autonomous apart from the held input, so every interval is solved
    on [0, dt]. By default: classical RK4 with `substeps` constant steps of exactly
    (t1 - t0) / substeps (`max_steps=substeps` makes diffrax fail rather than take a
    clipped extra step), and `DirectAdjoint` (discretise-then-optimise: its gradients are those of
    the discrete solution, exact up to round-off, unlike BacksolveAdjoint).
    """
    term = diffrax.ODETerm(lambda t, y, args: rhs(y, args[0], args[1]))
    if solver is None:
        solver, controller, max_steps = DiffraxRK4(), diffrax.ConstantStepSize(), substeps
    else:
        max_steps = 100_000
    t0, t1 = 0.0, dt

    def interval(x, u_k):
        sol = diffrax.diffeqsolve(
            term,
            solver,
            t0=t0,
            t1=t1,
            dt0=(t1 - t0) / substeps,
            y0=x,
            args=(u_k, theta),
            saveat=diffrax.SaveAt(t1=True),
            stepsize_controller=controller,
            adjoint=diffrax.DirectAdjoint(),
            max_steps=max_steps,
        )
        x_next = sol.ys[-1]
        return x_next, x_next

    _, xs = jax.lax.scan(interval, x0, u[:-1])
    return jnp.concatenate([x0[None], xs], axis=0)


#
# The test problems
#


@dataclasses.dataclass(frozen=True, eq=False)
class GradientCase:
    """Data and model of one identification problem, with the gradient taken at (theta, x0).

    Continuous-time problems give `rhs` and `dt` (the model is `Model.from_ode` with RK4
    and `substeps`); discrete-time ones give `step` instead. Several trajectories: x0 of
    shape (N, n_x), u (N, T, n_u), z (N, T, n_z).
    """

    name: str
    theta: Any
    x0: Any
    u: Any
    z: Any
    rhs: Callable | None = None
    dt: float | None = None
    substeps: int = 1
    step: Callable | None = None
    observe: Callable | None = None
    weight: Any = None
    penalty: Callable | None = None
    penalty_weight: float = 1.0

    @property
    def batched(self):
        return jnp.ndim(self.x0) == 2

    def model(self):
        if self.rhs is not None:
            return oj.Model.from_ode(
                self.rhs, self.dt, method="rk4", substeps=self.substeps, observe=self.observe
            )
        return oj.Model(self.step, self.observe)

    def cost_kwargs(self):
        return dict(weight=self.weight, penalty=self.penalty, penalty_weight=self.penalty_weight)

    def oracle_step(self):
        if self.rhs is not None:
            return own_step(self.rhs, self.dt, self.substeps)
        return self.step

    def _parts(self):
        observe = _identity if self.observe is None else self.observe
        U, Z = (self.u, self.z) if self.batched else (self.u[None], self.z[None])
        cost = lambda xs, th, u, z, loop: hand_cost(  # noqa: E731
            xs, th, u, z, observe, self.weight, self.penalty, self.penalty_weight, loop=loop
        )
        return U, Z, cost

    def oracle_a_cost(self, theta, x0):
        """C with our own RK4 (or the discrete step) in a Python for-loop, summed by hand.

        Meant to be differentiated eagerly (`jax.grad`, no outer `jax.jit`).
        """
        step = self.oracle_step()
        U, Z, cost = self._parts()
        x0s = x0 if self.batched else x0[None]
        total = 0.0
        for i in range(U.shape[0]):
            xs = loop_rollout(step, theta, x0s[i], U[i])
            total = total + cost(xs, theta, U[i], Z[i], True)
        return total / U.shape[0]

    def oracle_b_cost(self, theta, x0):
        """C with the rollout done by diffrax (classical RK4 from its Butcher tableau).

        Meant to be differentiated under `jax.jit`.
        """
        assert self.rhs is not None
        U, Z, cost = self._parts()
        x0s = x0 if self.batched else x0[None]
        rollout = lambda x0, u: diffrax_rollout(  # noqa: E731
            self.rhs, self.dt, self.substeps, theta, x0, u
        )
        xs = jax.vmap(rollout)(x0s, U) if self.batched else rollout(x0, self.u)[None]
        per_traj = [cost(xs[i], theta, U[i], Z[i], False) for i in range(U.shape[0])]
        return sum(per_traj) / U.shape[0]


def _rng(seed):
    return np.random.default_rng(seed)


def _perturb(tree, rng, scale):
    """theta or x0 moved away from the truth, so that residuals and gradients are non-trivial."""
    return jax.tree_util.tree_map(
        lambda a: jnp.asarray(a) * (1 + scale * rng.standard_normal(jnp.shape(a))), tree
    )


def _make(
    name,
    *,
    rhs,
    dt,
    theta_true,
    x0_true,
    u,
    noise,
    rng,
    substeps=1,
    observe=None,
    theta_scale=0.05,
    x0_shift=None,
    **kwargs,
):
    """Generate z by our own RK4 at the true values plus noise; perturb theta and x0."""
    obs = _identity if observe is None else observe
    step = own_step(rhs, dt, substeps)
    x0_true = jnp.asarray(x0_true)
    batched = x0_true.ndim == 2
    X0, U = (x0_true, u) if batched else (x0_true[None], u[None])
    zs = []
    for i in range(U.shape[0]):
        xs = loop_rollout(step, theta_true, X0[i], U[i])
        zs.append(jnp.stack([obs(x, uk, theta_true) for x, uk in zip(xs, U[i])]))
    z = jnp.stack(zs)
    z = z + noise * rng.standard_normal(z.shape)
    z = z if batched else z[0]
    theta = _perturb(theta_true, rng, theta_scale)
    shift = x0_shift if x0_shift is not None else 0.05 * rng.standard_normal(x0_true.shape)
    x0 = x0_true + shift
    return GradientCase(
        name, theta, x0, u, z, rhs=rhs, dt=dt, substeps=substeps, observe=observe, **kwargs
    )


def satellite_rhs(w, M, inertia):
    """Euler's equations (22) with a diagonal inertia I = theta: I w' = M - w x (I w)."""
    return (M - jnp.cross(w, inertia * w)) / inertia


def satellite(T=50, seed=0):
    """Section 4 of the paper: dt = 0.1 s, T = 50, M ~ N(1e-5, 1e-7), noise 1e-4 rad/s."""
    rng = _rng(seed)
    theta_true = jnp.array([0.0403, 0.0404, 0.0080])
    w0 = jnp.array([9.915e-6, -1.102e-3, 1.3179e-5])
    M = 1e-5 + 1e-7 * rng.standard_normal((T, 3))
    return _make(
        "satellite",
        rhs=satellite_rhs,
        dt=0.1,
        theta_true=theta_true,
        x0_true=w0,
        u=jnp.asarray(M),
        noise=1e-4,
        rng=rng,
        theta_scale=0.05,
        x0_shift=jnp.array([2e-5, -1e-4, 3e-5]),
    )


def pendulum_rhs(x, u, theta):
    """Damped pendulum, theta = [g/l, damping], u = applied angular acceleration."""
    phi, omega = x
    return jnp.stack([omega, -theta[0] * jnp.sin(phi) - theta[1] * omega + u[0]])


def angle_only(x, u, theta):
    del u, theta
    return x[:1]


EULER_DT = 0.05


def euler_pendulum_step(x, u, th):
    """An explicit Euler step of the damped pendulum, th = {"w0sq": g/l, "b": damping}, u
    the applied angular acceleration: a plain step (no integrator of the library's), so
    that `jax.grad` of a loss written with it is an independent reference."""
    q, v = x[0], x[1]
    dv = -th["w0sq"] * jnp.sin(q) - th["b"] * v + u[0]
    return jnp.stack([q + EULER_DT * v, v + EULER_DT * dv])


EULER_PENDULUM = oj.Model(euler_pendulum_step, angle_only, states=["q", "v"])


def pendulum(T=40, seed=1, substeps=2):
    """Pendulum observed through its angle only (n_z = 1 < n_x = 2), two RK4 substeps."""
    rng = _rng(seed)
    u = 0.5 * jnp.sin(0.3 * jnp.arange(T))[:, None]
    return _make(
        "pendulum",
        rhs=pendulum_rhs,
        dt=0.05,
        substeps=substeps,
        theta_true=jnp.array([9.81, 0.4]),
        x0_true=jnp.array([0.8, 0.0]),
        u=u,
        noise=1e-2,
        rng=rng,
        observe=angle_only,
    )


def lotka_volterra_rhs(x, u, theta):
    """Predator-prey, theta = [a, b, c, d], u = immigration into both populations."""
    a, b, c, d = theta
    prey, pred = x
    return jnp.stack([a * prey - b * prey * pred + u[0], c * prey * pred - d * pred + u[1]])


def lotka_volterra(T=40, seed=2):
    rng = _rng(seed)
    u = 0.05 * jnp.abs(jnp.asarray(rng.standard_normal((T, 2))))
    return _make(
        "lotka_volterra",
        rhs=lotka_volterra_rhs,
        dt=0.1,
        theta_true=jnp.array([1.1, 0.4, 0.1, 0.4]),
        x0_true=jnp.array([2.0, 1.0]),
        u=u,
        noise=0.02,
        rng=rng,
        weight=jnp.array([1.0, 2.5]),
    )


N_MASSES = 20


def chain_rhs(x, u, theta):
    """20 masses between two walls, linked by 21 springs with a cubic hardening term.

    x = [q (20 displacements), v (20 velocities)]; theta = {"k": (21,), "m": (20,),
    "c": () damping, "eps": () cubic stiffness}; u = force on the first mass.
    """
    q, v = x[:N_MASSES], x[N_MASSES:]
    ext = jnp.concatenate([jnp.zeros_like(q[:1]), q, jnp.zeros_like(q[:1])])
    stretch = ext[1:] - ext[:-1]  # (21,), spring j joins mass j-1 and mass j
    tension = theta["k"] * stretch + theta["eps"] * stretch**3
    force = tension[1:] - tension[:-1] - theta["c"] * v
    force = force.at[0].add(u[0])
    return jnp.concatenate([v, force / theta["m"]])


def chain_observe(x, u, theta):
    del u, theta
    return x[:N_MASSES:4]


def spring_chain(T=20, seed=3):
    rng = _rng(seed)
    theta_true = {
        "k": jnp.asarray(1.0 + 0.2 * rng.random(N_MASSES + 1)),
        "m": jnp.asarray(1.0 + 0.1 * rng.random(N_MASSES)),
        "c": jnp.asarray(0.05),
        "eps": jnp.asarray(0.3),
    }
    x0_true = jnp.concatenate([0.1 * jnp.sin(jnp.linspace(0, 3, N_MASSES)), jnp.zeros(N_MASSES)])
    u = jnp.asarray(np.sin(0.5 * np.arange(T))[:, None])
    return _make(
        "spring_chain",
        rhs=chain_rhs,
        dt=0.05,
        theta_true=theta_true,
        x0_true=x0_true,
        u=u,
        noise=1e-3,
        rng=rng,
        observe=chain_observe,
        x0_shift=0.01 * jnp.ones(2 * N_MASSES),
    )


def motor_rhs(x, u, theta):
    """DC motor: x = [current, speed], u = voltage, with Coulomb friction tanh(w / 0.1)."""
    i, w = x
    di = (u[0] - theta["R"] * i - theta["K"] * w) / theta["L"]
    dw = (theta["K"] * i - theta["b"] * w - theta["fc"] * jnp.tanh(w / 0.1)) / theta["J"]
    return jnp.stack([di, dw])


def motor_observe(x, u, theta):
    """Outputs that depend on u and theta: speed, torque K i and back-emf u - R i."""
    i, w = x
    return jnp.stack([w, theta["K"] * i, u[0] - theta["R"] * i])


def motor_observe_u_theta(T=30, seed=4):
    """Outputs depend on u and theta, and theta is a dict with an entry that nothing reads
    (`"unused"`, whose gradient must be exactly zero)."""
    rng = _rng(seed)
    theta_true = {
        "R": 1.0,
        "L": 0.5,
        "K": 0.1,
        "b": 0.2,
        "J": 0.02,
        "fc": 0.01,
        "unused": np.ones((2, 3)),
    }
    theta_true = {k: jnp.asarray(v) for k, v in theta_true.items()}
    u = jnp.asarray(np.where(np.arange(T) % 10 < 5, 1.0, -0.5)[:, None])
    return _make(
        "observe_u_theta_unused_entry",
        rhs=motor_rhs,
        dt=0.02,
        theta_true=theta_true,
        x0_true=jnp.array([0.0, 0.5]),
        u=u,
        noise=1e-3,
        rng=rng,
        observe=motor_observe,
    )


def van_der_pol_rhs(x, u, theta):
    p, q = x
    return jnp.stack([q, theta[0] * (1 - p**2) * q - theta[1] * p + u[0]])


def van_der_pol_observe(x, u, theta):
    del u, theta
    return jnp.stack([x[0], x[1], x[0] * x[1]])


def vdp_barrier(x, theta):
    """Exponential barrier on the oscillation amplitude, |x|^2 <= 4, and theta > 0."""
    return jnp.exp((jnp.sum(x**2) - 4.0) / 0.5) + 1e-2 * jnp.sum(jnp.exp(-theta / 0.5))


def van_der_pol_barrier(T=30, seed=6):
    """A non-diagonal, singular (rank 2) PSD weight Q on three outputs, and an exponential
    barrier penalty (Section 3.3) that depends on both x and theta."""
    rng = _rng(seed)
    L = jnp.array([[1.0, 0.0], [0.5, 1.0], [-0.3, 0.8]])
    Q = L @ L.T
    u = jnp.asarray(0.2 * rng.standard_normal((T, 1)))
    return _make(
        "nondiagonal_Q_barrier",
        rhs=van_der_pol_rhs,
        dt=0.1,
        theta_true=jnp.array([1.0, 1.0]),
        x0_true=jnp.array([1.5, 0.0]),
        u=u,
        noise=0.02,
        rng=rng,
        observe=van_der_pol_observe,
        weight=Q,
        penalty=vdp_barrier,
        penalty_weight=0.3,
    )


def duffing_rhs(x, u, theta):
    """Undamped, unforced (u = 0) Duffing oscillator: energy is conserved."""
    q, v = x
    return jnp.stack([v, (-theta["k"] * q - theta["eps"] * q**3 + u[0]) / theta["m"]])


def duffing_energy(x, theta):
    q, v = x
    return 0.5 * theta["m"] * v**2 + 0.5 * theta["k"] * q**2 + 0.25 * theta["eps"] * q**4


def energy_penalty(T=30, seed=8):
    """Penalty h = (E(x, theta) - E_ref)^2: the energy-conservation example of Section 3.3."""
    rng = _rng(seed)
    theta_true = {"k": jnp.asarray(2.0), "eps": jnp.asarray(0.5), "m": jnp.asarray(1.0)}
    x0_true = jnp.array([1.0, 0.0])
    E_ref = duffing_energy(x0_true, theta_true)

    def penalty(x, theta):
        return (duffing_energy(x, theta) - E_ref) ** 2

    return _make(
        "energy_penalty",
        rhs=duffing_rhs,
        dt=0.1,
        theta_true=theta_true,
        x0_true=x0_true,
        u=jnp.zeros((T, 1)),
        noise=1e-2,
        rng=rng,
        observe=angle_only,
        penalty=penalty,
        penalty_weight=2.0,
    )


def multi_trajectory(N=4, T=25, seed=9):
    """N = 4 pendulum experiments sharing theta, each with its own x0 and input."""
    rng = _rng(seed)
    t = jnp.arange(T)
    u = jnp.stack([0.3 * (i + 1) * jnp.sin(0.2 * (i + 1) * t)[:, None] for i in range(N)])
    x0_true = jnp.asarray(np.stack([[0.2 * (i + 1), 0.1 * (-1) ** i] for i in range(N)]))
    return _make(
        "multi_trajectory",
        rhs=pendulum_rhs,
        dt=0.05,
        substeps=1,
        theta_true=jnp.array([9.81, 0.4]),
        x0_true=x0_true,
        u=u,
        noise=1e-2,
        rng=rng,
        observe=angle_only,
        weight=jnp.array([3.0]),
    )


PROBLEMS = {
    "satellite": satellite,
    "pendulum": pendulum,
    "lotka_volterra": lotka_volterra,
    "spring_chain": spring_chain,
    "observe_u_theta_unused_entry": motor_observe_u_theta,
    "nondiagonal_Q_barrier": van_der_pol_barrier,
    "energy_penalty": energy_penalty,
    "multi_trajectory": multi_trajectory,
}


def cast(tree, dtype):
    """Every floating leaf of `tree` cast to `dtype` (None leaves stay None)."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=dtype), tree)


def observe_angle(x, u, p):
    """The pendulums' output: the angle."""
    return x[:1]


def pendulum_nonlinear_damping(x, u, p):
    """A driven pendulum with the damping 0.1 q' + 0.3 tanh(4 q') (not linear in q'):
    the truth of the hybrid tests, whose damping term a network learns."""
    q, v = x
    damping = 0.1 * v + 0.3 * jnp.tanh(4.0 * v)
    return jnp.stack([v, -p["w0sq"] * jnp.sin(q) - damping + p["g"] * u[0]])


def first_order_states(u, a=0.9, b=0.5, x0=1.0):
    """x[k+1] = a x[k] + b u[k, 0] from x[0] = x0, a loop in NumPy (float64): the states
    of the first-order model the stopping tests fit with an output offset."""
    x = np.empty(len(u))
    x[0] = x0
    for k in range(len(u) - 1):
        x[k + 1] = a * x[k] + b * u[k, 0]
    return x
