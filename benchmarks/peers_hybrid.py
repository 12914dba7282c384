"""The hybrid cascaded-tanks comparison of `benchmarks/peers.py`: oneshot_jax against
jax-sysid on a physics-plus-MLP model, with the same first-order optimiser budget.

Problem (`tanks_hybrid`, one definition for both tools): the basic two-tank Torricelli
model of `oneshot_jax.examples.cascaded_tanks` plus an MLP residual in the right-hand
side,

    dx/dt = basic_rhs(x, u, theta) + r(x, u),   r = residual.MLP(3 -> 16 tanh -> 2),
    y = x2 + c,

discretised by classical RK4 (2 substeps per Ts = 4 s, the pump voltage held), on the
estimation record (T = 1024). theta = {k1, k3, k4, c, r} (4 + 98 scalars) and x0 (2) are
estimated; r starts small but nonzero (so that every layer has a gradient). jax-sysid
gets the same `step` and `observe` functions as `state_fcn` / `output_fcn` and theta's
arrays as its parameter list, so both tools minimise the same function:

    C = (1/T) sum_k (yhat_k - y_k)^2

(oneshot_jax's eq. 5 with Q = 1; jax-sysid's default `output_loss`, sum / N, with its
regularisation off: rho_th = rho_x0 = 0, train_x0 = True). jax-sysid also clips the
states at +-xsat = 1000 V (its default), which the tanks never reach.

Measured, in one process (`measure`):

1. The value and gradient of C at the start. oneshot_jax: `value_and_grad` (the
   closed-form recursion), jitted; jax-sysid: its own function, captured from `fit` (the
   `JdJ` it hands to its Adam loop: `jax.value_and_grad` of its jitted loss, reverse-mode
   autodiff through its `lax.scan`), called as its Adam calls it and inside one `jax.jit`
   (as jaxopt's L-BFGS-B calls it). Medians of interleaved rounds (`timing.interleaved`);
   the losses and gradients of the two must agree.
2. Fits with the same budget, from the same start: Adam for `adam` epochs (the same
   rule and settings: lr for theta and x0 alike, b1 = 0.9, b2 = 0.99, eps = 1e-8,
   jax-sysid's defaults but b2 for oneshot_jax's Adam), then L-BFGS for `lbfgs`
   iterations. oneshot_jax: `fit(solver=[Adam(...), LBFGS(max_steps=lbfgs)])` (optax's
   L-BFGS with a zoom line search); jax-sysid: `Model.fit` with `adam_epochs`,
   `lbfgs_epochs` (scipy's L-BFGS-B through jaxopt; `lbfgs_epochs` caps both its
   iterations and its function evaluations). The wall time of the whole call: the first
   call in the process, and the median of `repeats` later calls, interleaved (jax-sysid
   builds and compiles new closures in every `fit`, so its later calls compile again),
   and the final C of each, recomputed by `oj.loss`.
3. Loss against time. Every call of 2 carries a clock: oneshot_jax's progress hook (a
   host callback after every step, which slows oneshot_jax's compiled loop a little),
   and for jax-sysid a wrapper of the `JdJ` its Adam loop calls and a callback on each
   L-BFGS-B iteration (its iterates are evaluated after the call). From the last call of
   each: the time each tool first reaches the worse tool's final loss, and the time to
   its first step (compilation, for jax-sysid every time).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import statistics
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from timing import block, interleaved

import oneshot_jax as oj
from oneshot_jax.examples import cascaded_tanks as tanks

WIDTH = 16
SUBSTEPS = 2
THETA0 = {"k1": 0.05, "k3": 0.05, "k4": 0.03, "c": 0.0}
"""The start of the basic model in `experiments/cascaded_tanks.py`."""
X0 = (5.0, 5.0)


@dataclasses.dataclass
class HybridTanks:
    """The problem, with theta's arrays as the flat list jax-sysid takes as parameters."""

    model: oj.Model
    theta0: dict
    x0: np.ndarray  # (2,)
    u: np.ndarray  # (T, 1)
    z: np.ndarray  # (T, 1)
    Ts: float
    static: object  # theta's non-array part (eqx.partition)
    treedef: object  # the structure of theta's arrays

    @property
    def T(self):
        return self.u.shape[0]

    def arrays(self, theta):
        """theta -> the list of its arrays (jax-sysid's `params`)."""
        return jax.tree_util.tree_leaves(eqx.filter(theta, eqx.is_inexact_array))

    def theta_of(self, arrays):
        """The inverse of `arrays` (traceable: used inside jax-sysid's loss)."""
        return eqx.combine(jax.tree_util.tree_unflatten(self.treedef, list(arrays)), self.static)

    def loss(self, theta, x0):
        return float(oj.loss(self.model, theta, jnp.asarray(x0), self.u, self.z))


def tanks_hybrid(width=WIDTH, seed=0):
    """The hybrid tanks problem (module docstring)."""
    data = oj.datasets.load_cascaded_tanks()
    u, y = data.u_est[:, None], data.y_est[:, None]
    # the MLP's features (x1, x2, u) centred and scaled by the data (the states are levels
    # in sensor volts, like y)
    offset = (y.mean(), y.mean(), u.mean())
    spread = (y.std(), y.std(), u.std())
    r = oj.residual.MLP(
        3,
        2,
        (width,),
        key=jax.random.PRNGKey(seed),
        scale=1e-3,  # V/s: a small correction to flows of order 0.01-0.1 V/s
        zero_last=False,
        input_offset=offset,
        input_scale=spread,
    )

    def rhs(x, u, theta):
        return tanks.basic_rhs(x, u, theta) + theta["r"](jnp.concatenate([x, u]))

    model = oj.Model.from_ode(rhs, data.Ts, method="rk4", substeps=SUBSTEPS, observe=tanks.observe)
    theta0 = {**{k: jnp.asarray(v) for k, v in THETA0.items()}, "r": r}
    params, static = eqx.partition(theta0, eqx.is_inexact_array)
    treedef = jax.tree_util.tree_structure(params)
    return HybridTanks(model, theta0, np.asarray(X0), u, y, data.Ts, static, treedef)


# ----------------------------------------------------------------------------- oneshot


class Clock(eqx.Module):
    """A `fit(progress=...)` hook that records (time, step, loss) after every step."""

    def open(self, total, description="fit"):
        del total, description
        return 0

    def close(self, bar_id):
        del bar_id

    def update(self, bar_id, offset, step, loss):
        del bar_id
        jax.debug.callback(_tick, offset + step, loss)

    def finish(self, bar_id, offset, step, loss):
        # called once after each solver's loop; `update` has recorded every step already
        del bar_id, offset, step, loss


_TICKS: list = []


def _tick(step, loss):
    _TICKS.append((time.perf_counter(), int(step), float(loss)))


def oneshot_solvers(lr, adam, lbfgs):
    return [oj.Adam(lr_theta=lr, lr_x0=lr, b2=0.99, max_steps=adam), oj.LBFGS(max_steps=lbfgs)]


def oneshot_fit(pb, solvers, clock=False):
    with warnings.catch_warnings():
        # the MLP's weights are not all identifiable: fit warns that the Jacobian at the
        # solution is rank-deficient (their standard deviations are inf), as expected
        warnings.simplefilter("ignore", UserWarning)
        res = _fit(pb, solvers, clock)
    return block(res.theta), np.asarray(res.x0), res


def _fit(pb, solvers, clock):
    return oj.fit(
        pb.model,
        pb.theta0,
        pb.x0,
        pb.u,
        pb.z,
        solver=solvers,
        estimate_x0=True,
        progress=Clock() if clock else False,
    )


# ---------------------------------------------------------------------------- jax-sysid


def sysid_model(pb, lr, adam, lbfgs):
    from jax_sysid.models import Model

    m = Model(
        2,
        1,
        1,
        state_fcn=lambda x, u, P: pb.model.step(x, u, pb.theta_of(P)),
        output_fcn=lambda x, u, P: pb.model.observe(x, u, pb.theta_of(P)),
        Ts=pb.Ts,
    )
    m.init(params=pb.arrays(pb.theta0), x0=pb.x0)
    m.loss(rho_x0=0.0, rho_th=0.0, train_x0=True)
    m.optimization(adam_eta=lr, adam_epochs=adam, lbfgs_epochs=lbfgs, iprint=-1)
    return m


def sysid_fit(pb, lr, adam, lbfgs):
    m = sysid_model(pb, lr, adam, lbfgs)
    with contextlib.redirect_stdout(io.StringIO()):  # it prints "L-BFGS-B done in ..."
        m.fit(pb.z.copy(), pb.u.copy())
    return pb.theta_of(m.params), np.asarray(m.x0), m


class _Captured(Exception):
    pass


@contextlib.contextmanager
def _patched(module, name, value):
    old = getattr(module, name)
    setattr(module, name, value)
    try:
        yield
    finally:
        setattr(module, name, old)


def sysid_gradient(pb):
    """jax-sysid's own value-and-gradient function of its loss and its variables at the
    start (the parameter arrays, then x0), taken from the first call of its Adam loop."""
    import jax_sysid.models as jsm

    got = {}

    def grab(JdJ, z, *args, **kwargs):
        got["JdJ"], got["z"] = JdJ, [jnp.array(a) for a in z]
        raise _Captured

    m = sysid_model(pb, 1e-3, 1, 0)
    with _patched(jsm, "adam_solver", grab), contextlib.suppress(_Captured):
        m.fit(pb.z.copy(), pb.u.copy())
    return got["JdJ"], got["z"]


def sysid_fit_clocked(pb, lr, adam, lbfgs):
    """`sysid_fit` with (time, loss) recorded at every Adam epoch and (time, iterate) at
    every L-BFGS-B iteration."""
    import jax_sysid.models as jsm
    import jaxopt

    adam_ticks, lbfgs_ticks = [], []
    adam_solver = jsm.adam_solver

    def clocked_adam(JdJ, z, *args, **kwargs):
        def JdJ_clocked(z):
            f, df = JdJ(z)
            adam_ticks.append((time.perf_counter(), float(f)))
            return f, df

        return adam_solver(JdJ_clocked, z, *args, **kwargs)

    def on_iteration(z):
        lbfgs_ticks.append((time.perf_counter(), jax.tree_util.tree_map(np.asarray, z)))

    class Jaxopt:  # jaxopt, with the iteration callback set on its scipy minimisers
        def __getattr__(self, name):
            return getattr(jaxopt, name)

        @staticmethod
        def ScipyMinimize(**kw):
            return jaxopt.ScipyMinimize(callback=on_iteration, **kw)

        @staticmethod
        def ScipyBoundedMinimize(**kw):
            return jaxopt.ScipyBoundedMinimize(callback=on_iteration, **kw)

    with _patched(jsm, "adam_solver", clocked_adam), _patched(jsm, "jaxopt", Jaxopt()):
        t0 = time.perf_counter()
        theta, x0, m = sysid_fit(pb, lr, adam, lbfgs)
        wall = time.perf_counter() - t0
    # jax-sysid's Adam records J before each update (epoch k: the loss of iterate k - 1)
    # and returns the best iterate; its L-BFGS iterates are [params..., x0].
    ticks = [(t - t0, f) for t, f in adam_ticks]
    n = len(pb.arrays(pb.theta0))
    ticks += [(t - t0, pb.loss(pb.theta_of(z[:n]), z[n])) for t, z in lbfgs_ticks]
    return theta, x0, wall, ticks, m


# ------------------------------------------------------------------------------ measure


def _flat_grad(pb, g_theta, g_x0):
    return np.concatenate([np.ravel(a) for a in (*pb.arrays(g_theta), g_x0)])


def first_time(ticks, target):
    """The first recorded time at which the loss is <= target (None if never)."""
    return next((t for t, f in ticks if f <= target), None)


def measure(lr=1e-3, adam=1000, lbfgs=300, repeats=3, grad_repeats=15, log=print):
    """Run the three measurements of the module docstring; returns a dict of numbers."""
    import importlib.metadata as md

    pb = tanks_hybrid()
    model, u, z = pb.model, pb.u, pb.z
    out = {
        "T": pb.T,
        "n_theta": int(oj.residual.count_parameters(pb.theta0)),
        "width": WIDTH,
        "substeps": SUBSTEPS,
        "lr": lr,
        "adam": adam,
        "lbfgs": lbfgs,
        "jax_sysid": md.version("jax-sysid"),
    }

    # 1. value and gradient at the start
    vg_one = eqx.filter_jit(lambda th, x0: oj.value_and_grad(model, th, x0, u, z))
    sim = eqx.filter_jit(lambda th, x0: oj.loss(model, th, x0, u, z))
    JdJ, z0 = sysid_gradient(pb)
    JdJ_jit = jax.jit(JdJ)
    th0, x00 = pb.theta0, jnp.asarray(pb.x0)
    C1, (g_th, g_x0) = vg_one(th0, x00)
    C2, g2 = JdJ(z0)
    C3, g3 = JdJ_jit(z0)
    g1 = _flat_grad(pb, g_th, g_x0)
    g2, g3 = (np.concatenate([np.ravel(a) for a in g]) for g in (g2, g3))
    scale = np.max(np.abs(g2))
    out.update(
        loss0=float(C1),
        loss_rel_diff=abs(float(C1) / float(C2) - 1),
        grad_rel_diff=float(np.max(np.abs(g1 - g2)) / scale),
        grad_rel_diff_jit=float(np.max(np.abs(g3 - g2)) / scale),
    )
    if out["loss_rel_diff"] > 1e-10 or out["grad_rel_diff"] > 1e-6:
        raise AssertionError(f"the two definitions disagree at the start: {out}")
    times = interleaved(
        {
            "simulate": lambda: sim(th0, x00),
            "oneshot": lambda: vg_one(th0, x00),
            "sysid_jit": lambda: JdJ_jit(z0),
            "sysid_adam": lambda: JdJ(z0),
        },
        repeats=grad_repeats,
    )
    out["grad_s"] = times
    log(
        "tanks_hybrid  gradient: oneshot_jax "
        + ", ".join(f"{k} {1e3 * v:.3g} ms" for k, v in times.items())
    )

    # 2 and 3. fits with the same budget, every call clocked (see the module docstring);
    # the first call of each tool, then `repeats` rounds interleaved.
    solvers = oneshot_solvers(lr, adam, lbfgs)

    def run_oneshot():
        _TICKS.clear()
        t0 = time.perf_counter()
        theta, x0, res = oneshot_fit(pb, solvers, clock=True)
        wall = time.perf_counter() - t0
        ticks = [(t - t0, f) for t, _, f in _TICKS]
        return theta, x0, wall, ticks, {"steps": int(res.num_steps), "solver_s": res.wall_time}

    def run_sysid():
        theta, x0, wall, ticks, m = sysid_fit_clocked(pb, lr, adam, lbfgs)
        return theta, x0, wall, ticks, {"loss_reported": float(m.Jopt)}

    runs = {"oneshot": run_oneshot, "sysid": run_sysid}
    fits = {k: {"wall_s": []} for k in runs}
    last = {}
    for rnd in range(repeats + 1):
        names = list(runs)[rnd % 2 :] + list(runs)[: rnd % 2]
        for name in names:
            theta, x0, wall, ticks, extra = runs[name]()
            f = fits[name]
            if rnd == 0:
                f["first_s"] = wall
                f["loss"] = pb.loss(theta, x0)
                f.update(extra)
                log(f"tanks_hybrid  {name:8s} first call {wall:.3g} s  C = {f['loss']:.6e}")
            else:
                f["wall_s"].append(wall)
                last[name] = ticks
    target = max(fits["oneshot"]["loss"], fits["sysid"]["loss"])
    out["target_loss"] = target
    for name, f in fits.items():
        ticks = last.get(name, [])
        f["wall_median_s"] = statistics.median(f["wall_s"]) if f["wall_s"] else None
        f["time_to_target_s"] = first_time(ticks, target * (1 + 1e-9))
        f["first_step_s"] = ticks[0][0] if ticks else None
        f["ticks"] = len(ticks)
        log(f"tanks_hybrid  {name:8s} later calls {f['wall_median_s']:.3g} s")
    out["fits"] = fits
    return out


# ------------------------------------------------------------------------------- report


def _t(s):
    from timing import fmt_time

    return fmt_time(s)


def _x(a, b):
    return "—" if a is None or b is None or b <= 0 else f"{a / b:.3g}x"


def fmt_hybrid(h):
    """The section of the report: the gradient table, the fit table and one computed
    sentence per comparison (who is faster, who ends lower)."""
    g, f = h["grad_s"], h["fits"]
    one, sys_ = f["oneshot"], f["sysid"]
    L = [
        "### (d) hybrid cascaded tanks: oneshot_jax against jax-sysid",
        "",
        f"Basic Torricelli model + MLP residual (3 -> {h['width']} tanh -> 2) in the "
        f"right-hand side, RK4 with {h['substeps']} substeps per sample, estimation record "
        f"(T = {h['T']}); {h['n_theta']} parameters and x0 (2) estimated; C = mean squared "
        f"simulation error, C0 = {h['loss0']:.6e} at the start. The same `step` and "
        f"`observe` serve as jax-sysid's `state_fcn` and `output_fcn` (regularisation off). "
        f"At the start the two tools' C differ by {h['loss_rel_diff']:.1e} (relative) and "
        f"their gradients by {h['grad_rel_diff']:.1e} (max. difference / max. entry).",
        "",
        "Value and gradient of C at the start (median time per call, compiled, after "
        "warm-up, rounds interleaved):",
        "",
        "| call | time | / one simulation | / oneshot_jax |",
        "|---|---|---|---|",
    ]
    rows = (
        ("one simulation: `oj.loss`, jitted", "simulate"),
        ("oneshot_jax `value_and_grad` (closed form), jitted", "oneshot"),
        ("jax-sysid `JdJ` (autodiff through its scan) in one `jax.jit`", "sysid_jit"),
        ("jax-sysid `JdJ` as its Adam loop calls it (grad of its jitted loss)", "sysid_adam"),
    )
    for label, k in rows:
        ratio = g[k] / g["simulate"]
        L.append(f"| {label} | {_t(g[k])} | {ratio:.3g} | {_x(g[k], g['oneshot'])} |")
    L += [
        "",
        f"Fits from the same start with the same budget: Adam, {h['adam']} epochs (lr = "
        f"{h['lr']:g} for theta and x0, b2 = 0.99), then L-BFGS, {h['lbfgs']} iterations "
        "(oneshot_jax: optax L-BFGS, zoom line search; jax-sysid: scipy L-BFGS-B, "
        "`lbfgs_epochs` also caps its function evaluations). Wall time of the whole call; "
        f"'later calls': median of {len(one['wall_s'])} (jax-sysid compiles again in every "
        f"call); C_target = the worse final C = {h['target_loss']:.6e}. The last two "
        "columns come from the clock of the last call of each (whose wall time may differ "
        "from the median).",
        "",
        "| tool | first call | later calls | ratio to oneshot_jax (later) | before the first "
        "step (later call) | final C | time to C_target (later call) |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, r in (
        (f"oneshot_jax `fit(solver=[Adam, LBFGS])`, {one['steps']} steps", one),
        ("jax-sysid `Model.fit` (adam_epochs, lbfgs_epochs)", sys_),
    ):
        L.append(
            f"| {label} | {_t(r['first_s'])} | {_t(r['wall_median_s'])} | "
            f"{_x(r['wall_median_s'], one['wall_median_s'])} | {_t(r['first_step_s'])} | "
            f"{r['loss']:.6e} | {_t(r['time_to_target_s'])} |"
        )
    L += ["", *hybrid_sentences(h), ""]
    return L


def hybrid_sentences(h):
    """Where each tool wins, computed from the numbers."""
    g, f = h["grad_s"], h["fits"]
    one, sys_ = f["oneshot"], f["sysid"]
    out = []
    fast = "oneshot_jax" if g["oneshot"] < g["sysid_jit"] else "jax-sysid"
    out.append(
        f"Gradient: {fast} is faster ({g['sysid_jit'] / g['oneshot']:.3g}x, jax-sysid / "
        f"oneshot_jax, both jitted)."
    )
    for key, what in (("first_s", "first call"), ("wall_median_s", "later calls")):
        a, b = one[key], sys_[key]
        winner = "oneshot_jax" if a < b else "jax-sysid"
        out.append(f"Fit, {what}: {winner} is faster (oneshot_jax {_t(a)}, jax-sysid {_t(b)}).")
    lo = "oneshot_jax" if one["loss"] < sys_["loss"] else "jax-sysid"
    out.append(
        f"Final loss: {lo} ends lower (C = {one['loss']:.6e} oneshot_jax, "
        f"{sys_['loss']:.6e} jax-sysid: the two L-BFGS implementations differ)."
    )
    return [" ".join(out)]
