"""One runner per tool for `benchmarks/peers.py`.

Every runner minimises the same cost C (see `peers_problems`) over the same variables
p = (theta, free entries of each record's x0), from the same start, and returns the
solution as that vector. `run()` is the timed call; whatever a runner builds on its first
call (JIT compilations, a CasADi graph and solver) it keeps for later calls, as a user
who fits the same model again would, so the first call is the time *with* compilation
and the later calls the time *without*.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import re
import time

import jax
import jax.numpy as jnp
import numpy as np
from timing import interleaved
from timing import versions as _versions

import oneshot_jax as oj

# ------------------------------------------------------------------ shared JAX residual


def jax_residual(pb, mean=True):
    """r(p, U, Z, X0) = zhat - z stacked, divided by sqrt(N T) with `mean` so that
    ||r||^2 = C; the data are arguments, not baked-in constants."""
    n_th, free, N, T, n_z, m = pb.n_th, np.asarray(pb.x0_free, int), pb.N, pb.T, pb.n_z, pb.m
    step = pb.model.step
    scale = 1.0 / np.sqrt(N * T) if mean else 1.0

    def rollout(th, x0, u):
        def body(x, uk):
            xn = step(x, uk, th)
            return xn, xn

        _, xs = jax.lax.scan(body, x0, u[:-1])
        return jnp.concatenate([x0[None], xs], axis=0)

    def residual(p, U, Z, X0):
        th = pb.unflat(p[:n_th])
        if m:
            X0 = X0.at[:, free].set(p[n_th:].reshape(N, m))
        xs = jax.vmap(rollout, in_axes=(None, 0, 0))(th, X0, U)
        return ((xs[..., :n_z] - Z) * scale).reshape(-1)

    return residual


def make_loss(pb):
    """The common evaluator: C at a solution vector (jitted, used for every tool)."""
    res = jax.jit(jax_residual(pb))
    U, Z, X0 = (jnp.asarray(a) for a in (pb.U, pb.Z, pb.X0))
    return lambda p: float(jnp.sum(res(jnp.asarray(p, jnp.float64), U, Z, X0) ** 2))


class Tool:
    label = ""
    method = ""

    def __init__(self, pb):
        self.pb = pb
        self.p0 = pb.p0()

    def run(self) -> dict:  # {"p": vector, "iterations", "fevals", "stop", ...}
        raise NotImplementedError


# ----------------------------------------------------------------------------- oneshot


class Oneshot(Tool):
    """oneshot_jax.fit with a structured least-squares solver on the closed-form Jacobian."""

    SOLVERS = {"levenberg_marquardt": oj.LevenbergMarquardt, "gauss_newton": oj.GaussNewton}

    def __init__(self, pb, solver):
        super().__init__(pb)
        self.solver = self.SOLVERS[solver](max_steps=200)
        self.label = f"oneshot_jax fit(solver={type(self.solver).__name__}())"
        self.method = {"levenberg_marquardt": "LM", "gauss_newton": "GN"}[
            solver
        ] + ", closed-form forward sensitivities, Schur complement over the records' x0"
        single = pb.N == 1
        self.u = pb.U[0] if single else pb.U
        self.z = pb.Z[0] if single else pb.Z
        self.x0 = pb.X0[0] if single else pb.X0
        mask = np.zeros(pb.n_x, bool)
        mask[list(pb.x0_free)] = True
        self.estimate_x0 = bool(mask.all()) if (mask.all() or not mask.any()) else mask
        self.box = pb.box()

    def run(self):
        res = oj.fit(
            self.pb.model,
            self.pb.theta0,
            self.x0,
            self.u,
            self.z,
            solver=self.solver,
            constraints=self.box,
            estimate_x0=self.estimate_x0,
        )
        X0 = np.atleast_2d(np.asarray(res.x0))
        p = np.concatenate([self.pb.flat(res.theta), X0[:, list(self.pb.x0_free)].reshape(-1)])
        return {
            "p": p,
            "iterations": int(res.num_steps),
            "fevals": None,
            "stop": res.status,
            "solver_s": float(res.wall_time),
            "loss_reported": float(res.loss),
        }


# ------------------------------------------------------------------------------- scipy


class _ScipyBase(Tool):
    def __init__(self, pb):
        super().__init__(pb)
        # least_squares gets the plain output errors zhat - z, as a user writes them
        self.res = jax.jit(jax_residual(pb, mean=False))
        self.args = tuple(jnp.asarray(a) for a in (pb.U, pb.Z, pb.X0))

    def fun(self, p):
        self.calls += 1
        return np.asarray(self.res(jnp.asarray(p), *self.args))

    def bounds_vec(self):
        lo = np.concatenate([self.pb.th_lower, np.full(self.pb.n_var - self.pb.n_th, -np.inf)])
        return lo, np.full(self.pb.n_var, np.inf)


class ScipyLM(_ScipyBase):
    label = "scipy least_squares(method='lm')"
    method = (
        "MINPACK LM (x_scale='jac', its default), 2-point finite-difference Jacobian, "
        "residual zhat - z jitted in JAX, no bounds"
    )

    def run(self):
        import scipy.optimize as so

        self.calls = 0
        r = so.least_squares(self.fun, self.p0, method="lm")
        return {"p": r.x, "iterations": None, "fevals": self.calls, "stop": f"status {r.status}"}


class ScipyTRF(_ScipyBase):
    label = "scipy least_squares(method='trf')"

    def __init__(self, pb):
        super().__init__(pb)
        self.sparsity = None
        if pb.N > 1 and pb.m:
            # Window i's residuals depend on theta and on window i's x0 only; with the
            # sparsity given, scipy groups the columns: n_th + m evaluations per Jacobian.
            import scipy.sparse as sp

            rows = pb.N * pb.T * pb.n_z
            S = sp.lil_matrix((rows, pb.n_var), dtype=np.int8)
            S[:, : pb.n_th] = 1
            per = pb.T * pb.n_z
            for i in range(pb.N):
                S[i * per : (i + 1) * per, pb.n_th + i * pb.m : pb.n_th + (i + 1) * pb.m] = 1
            self.sparsity = S.tocsr()
        self.method = (
            "trust-region reflective, bounds, x_scale='jac', 2-point finite differences, "
            "residual jitted in JAX; where the Jacobian is sparse (EMPS: each window's "
            "residuals depend on theta and that window's x0 only) the documented route: "
            "jac_sparsity (column grouping, n_theta + n_x0 evaluations per Jacobian) with "
            "tr_solver='lsmr'; elsewhere tr_solver='exact'"
        )

    def run(self):
        import scipy.optimize as so

        kw = (
            {"jac_sparsity": self.sparsity, "tr_solver": "lsmr"}
            if self.sparsity is not None
            else {}
        )
        self.calls = 0
        # x_scale='jac': the documented remedy for variables of different magnitudes ('lm'
        # uses it by default); with the default x_scale = 1, trf + lsmr crawls on EMPS
        # (thousands of iterations at 5x the optimal loss).
        r = so.least_squares(
            self.fun, self.p0, method="trf", bounds=self.bounds_vec(), x_scale="jac", **kw
        )
        return {"p": r.x, "iterations": r.njev, "fevals": self.calls, "stop": f"status {r.status}"}


class ScipySLSQP(_ScipyBase):
    label = "scipy minimize(method='SLSQP')"
    method = (
        "SLSQP, 2-point finite-difference gradient, bounds, default tolerances, loss jitted in JAX"
    )

    def __init__(self, pb):
        super().__init__(pb)
        res = jax_residual(pb)
        self.loss = jax.jit(lambda p, U, Z, X0: jnp.sum(res(p, U, Z, X0) ** 2))

    def run(self):
        import scipy.optimize as so

        lo, hi = self.bounds_vec()
        bounds = [(None if not np.isfinite(a) else a, None) for a in lo]
        self.calls = 0

        def f(p):
            self.calls += 1
            return float(self.loss(jnp.asarray(p), *self.args))

        r = so.minimize(f, self.p0, method="SLSQP", bounds=bounds)
        return {
            "p": r.x,
            "iterations": int(r.nit),
            "fevals": self.calls,
            "stop": f"{'success' if r.success else 'fail'}: {r.message}",
        }


# ------------------------------------------------------------------------------ casadi


class CasadiIpopt(Tool):
    label = "CasADi + IPOPT"
    method = (
        "single shooting per record (MapAccum over the RK4 step, Map over records), "
        "exact derivatives, Gauss-Newton Hessian J^T J, variables scaled to O(1), "
        "objective normalised by its starting value (the CasADi sysid example)"
    )

    def __init__(self, pb, print_level=0):
        super().__init__(pb)
        self.solver = None
        self.print_level = print_level

    def build(self):
        import casadi as ca

        pb = self.pb
        x = ca.SX.sym("x", pb.n_x)
        u = ca.SX.sym("u", pb.n_u)
        p = ca.SX.sym("p", pb.n_th)
        th = pb.unflat(p)
        h = pb.dt
        k1 = pb.rhs_casadi(x, u, th)
        k2 = pb.rhs_casadi(x + 0.5 * h * k1, u, th)
        k3 = pb.rhs_casadi(x + 0.5 * h * k2, u, th)
        k4 = pb.rhs_casadi(x + h * k3, u, th)
        step = ca.Function("step", [x, u, p], [x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)])
        T, N, m = pb.T, pb.N, pb.m
        sim = step.mapaccum("sim", T - 1)
        x0s = ca.MX.sym("x0", pb.n_x)
        Uw = ca.MX.sym("U", pb.n_u, T)
        Pw = ca.MX.sym("P", pb.n_th)
        Xw = ca.horzcat(x0s, sim(x0s, Uw[:, : T - 1], ca.repmat(Pw, 1, T - 1)))
        window = ca.Function("window", [x0s, Uw, Pw], [Xw[: pb.n_z, :]])
        windows = window.map(N)

        V = ca.MX.sym("V", pb.n_var)
        th_s = pb.th_scale
        P = V[: pb.n_th] * ca.DM(th_s)
        X0 = ca.DM(pb.X0.T)  # (n_x, N)
        if m:
            free = list(pb.x0_free)
            xs_scale = pb.x0_scale[free]
            Xfree = ca.reshape(V[pb.n_th :], m, N) * ca.repmat(ca.DM(xs_scale), 1, N)
            rows = []
            for j in range(pb.n_x):
                rows.append(Xfree[free.index(j), :] if j in free else X0[j, :])
            X0 = ca.vertcat(*rows)
        Ucat = ca.DM(np.concatenate(list(pb.U), axis=0).T)  # (n_u, N T)
        Zcat = ca.DM(np.concatenate(list(pb.Z), axis=0).T)  # (n_z, N T)
        Y = windows(X0, Ucat, ca.repmat(P, 1, N))
        e = ca.vec(Y - Zcat) / np.sqrt(N * T)
        self.v_scale = np.concatenate([th_s, np.tile(pb.x0_scale[list(pb.x0_free)], N)])
        v0 = self.p0 / self.v_scale
        f0 = float(ca.Function("f", [V], [ca.dot(e, e)])(v0))
        f = 0.5 * ca.dot(e, e) / f0
        J = ca.jacobian(e, V)
        H = ca.triu(ca.mtimes(J.T, J)) / f0
        sigma = ca.MX.sym("sigma")
        # C code generation + compilation, as the example does when a compiler is found
        if ca.Importer.has_plugin("clang"):
            jit = {"jit": True, "compiler": "clang"}
        elif ca.Importer.has_plugin("shell"):
            jit = {"jit": True, "compiler": "shell"}
        else:
            jit = {}
        self.jit = jit.get("compiler", "none")
        hess = ca.Function(
            "nlp_hess_l",
            {"x": V, "lam_f": sigma, "hess_gamma_x_x": sigma * H},
            ["x", "p", "lam_f", "lam_g"],
            ["hess_gamma_x_x"],
            jit,
        )
        opts = {
            "hess_lag": hess,
            "print_time": False,
            "ipopt.print_level": self.print_level,
            "ipopt.sb": "yes",
            **jit,
        }
        self.solver = ca.nlpsol("solver", "ipopt", {"x": V, "f": f}, opts)
        lo = np.concatenate([pb.th_lower / th_s, np.full(pb.n_var - pb.n_th, -np.inf)])
        self.lbx, self.v0 = lo, v0

    def run(self):
        t0 = time.perf_counter()
        first = self.solver is None
        if first:
            self.build()
        t_build = time.perf_counter() - t0
        sol = self.solver(x0=self.v0, lbx=self.lbx)
        st = self.solver.stats()
        out = {
            "p": np.asarray(sol["x"]).ravel() * self.v_scale,
            "iterations": int(st["iter_count"]),
            "fevals": st.get("n_call_nlp_f"),
            "stop": st["return_status"],
        }
        if first:
            out["build_s"] = t_build
        return out


# ---------------------------------------------------------------------------- jax-sysid


class JaxSysid(Tool):
    label = "jax-sysid Model.fit"
    method = (
        "L-BFGS-B (jaxopt.ScipyBoundedMinimize) on the jax.grad of the simulation loss, "
        "rho_th = rho_x0 = 0 (no regularisation), parameters scaled to O(1), "
        "records passed as a list of experiments"
    )

    def __init__(self, pb):
        super().__init__(pb)
        from jax_sysid.models import Model as JSModel

        self.JSModel = JSModel
        th_s = pb.th_scale
        step, unflat, n_z = pb.model.step, pb.unflat, pb.n_z
        self.state_fcn = lambda x, u, params: step(x, u, unflat(params[0] * th_s))  # noqa: E731
        self.output_fcn = lambda x, u, params: x[:n_z]  # noqa: E731
        self.th_s = th_s
        single = pb.N == 1
        self.U = pb.U[0] if single else [a for a in pb.U]
        self.Y = pb.Z[0] if single else [a for a in pb.Z]
        self.x0 = pb.X0[0] if single else [a for a in pb.X0]
        self.train_x0 = pb.m > 0
        if self.train_x0 and pb.m != pb.n_x:
            raise ValueError("jax-sysid trains all of x0 or none")

    def run(self):
        pb = self.pb
        m = self.JSModel(
            pb.n_x, pb.n_z, pb.n_u, state_fcn=self.state_fcn, output_fcn=self.output_fcn, Ts=pb.dt
        )
        m.init(params=[pb.flat(pb.theta0) / self.th_s], x0=self.x0)
        m.loss(rho_x0=0.0, rho_th=0.0, train_x0=self.train_x0)
        lo = pb.th_lower / self.th_s
        bounded = bool(np.isfinite(lo).any())
        kw = {}
        if bounded:
            kw = {"params_min": [jnp.asarray(lo)], "params_max": [jnp.full(pb.n_th, jnp.inf)]}
            if self.train_x0 and pb.N > 1:
                # jax-sysid 1.0.1 cannot build default x0 bounds for a list of experiments
                # (jnp.ones_like on a list): give them explicitly, unbounded.
                kw["x0_min"] = [jnp.full(pb.n_x, -jnp.inf)] * pb.N
                kw["x0_max"] = [jnp.full(pb.n_x, jnp.inf)] * pb.N
        m.optimization(lbfgs_epochs=1000, iprint=-1, **kw)
        buf = io.StringIO()
        # copies, because fit() rewrites the lists it is given
        U = [a.copy() for a in self.U] if isinstance(self.U, list) else self.U
        Y = [a.copy() for a in self.Y] if isinstance(self.Y, list) else self.Y
        with contextlib.redirect_stdout(buf):
            m.fit(Y, U)
        found = re.findall(r"done in (\d+) iterations", buf.getvalue())
        th = np.asarray(m.params[0]) * self.th_s
        X0 = np.atleast_2d(np.asarray(m.x0)) if self.train_x0 else pb.X0
        p = np.concatenate([th, X0[:, list(pb.x0_free)].reshape(-1)])
        return {
            "p": p,
            "iterations": int(found[-1]) if found else None,
            "fevals": None,
            "stop": "L-BFGS-B",
            "tool_t_solve_s": float(m.t_solve),
        }


# --------------------------------------------------------------------------- optimistix


class OptimistixLM(Tool):
    label = "optimistix LevenbergMarquardt"
    method = (
        "dense LM, Jacobian by JAX forward-mode autodiff (jac='fwd', jacfwd of the whole "
        "rollout), lineax QR (the default), rtol = atol = 1e-8, no bounds"
    )

    def __init__(self, pb):
        super().__init__(pb)
        import optimistix as optx

        self.optx = optx
        res = jax_residual(pb, mean=False)
        self.fn = lambda p, args: res(p, *args)  # noqa: E731
        self.args = tuple(jnp.asarray(a) for a in (pb.U, pb.Z, pb.X0))
        self.solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)

    def run(self):
        sol = self.optx.least_squares(
            self.fn,
            self.solver,
            jnp.asarray(self.p0),
            args=self.args,
            options={"jac": "fwd"},
            max_steps=256,
            throw=False,
        )
        p = np.asarray(jax.block_until_ready(sol.value))
        ok = sol.result == self.optx.RESULTS.successful
        return {
            "p": p,
            "iterations": int(sol.stats["num_steps"]),
            "fevals": None,
            "stop": "successful" if ok else "max_steps / failed",
        }


TOOLS = {
    "oneshot_lm": lambda pb: Oneshot(pb, "levenberg_marquardt"),
    "oneshot_gn": lambda pb: Oneshot(pb, "gauss_newton"),
    "scipy_lm": ScipyLM,
    "scipy_trf": ScipyTRF,
    "scipy_slsqp": ScipySLSQP,
    "casadi_ipopt": CasadiIpopt,
    "jax_sysid": JaxSysid,
    "optimistix_lm": OptimistixLM,
}
ONESHOT = ("oneshot_lm", "oneshot_gn")
LABELS = {
    "oneshot_lm": "oneshot_jax fit(solver=LevenbergMarquardt())",
    "oneshot_gn": "oneshot_jax fit(solver=GaussNewton())",
    "scipy_lm": ScipyLM.label,
    "scipy_trf": ScipyTRF.label,
    "scipy_slsqp": ScipySLSQP.label,
    "casadi_ipopt": CasadiIpopt.label,
    "jax_sysid": JaxSysid.label,
    "optimistix_lm": OptimistixLM.label,
}


def versions():
    out = _versions(("lineax", "casadi", "jax-sysid", "jaxopt"))
    try:
        import casadi as ca

        out["ipopt"] = "bundled with casadi " + ca.__version__
    except ImportError:
        pass
    return out


# ----------------------------------------------------------------------- diagnostics


def jacobian_timings(pb, repeats=20):
    """Cost of one trajectory Jacobian against one simulation, for the first record:

    - `simulate`: the residuals (one rollout), jitted;
    - `jacfwd`: jax.jacfwd of the residuals (forward-mode autodiff through the rollout);
    - `closed_jacobian`: oneshot_jax's forward-sensitivity Jacobian
      (`_sensitivity.trajectory_jacobian`) with strategy "jacobian": one rollout, then
      A = df/dx and B = df/dtheta at every step at once (vmapped jacfwd, Remark 1), then
      a scan of S <- A S + [B, 0];
    - `closed_vjp`: the same recursion matrix-free (strategy "vjp"), S <- vmap(jvp f)(S)
      inside the scan, never forming A.
    `fit` picks "jacobian" for n_x <= 16 ("auto"). Medians in seconds over interleaved
    rounds of one call each (`timing.interleaved`), after a warm-up call.
    """
    from oneshot_jax.internal import Cost, sensitivity_strategy, trajectory_jacobian

    u, z, x0 = (jnp.asarray(a[0]) for a in (pb.U, pb.Z, pb.X0))
    free = np.asarray(pb.x0_free, int)
    pt, px = jnp.asarray(pb.flat(pb.theta0)), x0[free]
    scale = 1.0 / np.sqrt(pb.T)
    x0_of = lambda q: x0.at[free].set(q)  # noqa: E731

    cost = Cost(None, None, jnp.asarray(0.0))

    def closed_form(strategy):
        def jac(pt, px):
            lin = trajectory_jacobian(
                pb.model, cost, pb.unflat, pt, x0_of, px, u, z, scale=scale, strategy=strategy
            )
            return lin.r, lin.Jt, lin.Jx

        return jax.jit(jac)

    one = dataclasses.replace(pb, U=pb.U[:1], Z=pb.Z[:1], X0=pb.X0[:1])
    res = jax_residual(one)
    U1, Z1, X01 = (jnp.asarray(a) for a in (one.U, one.Z, one.X0))
    p0 = jnp.asarray(one.p0())
    fns = {
        "simulate": (jax.jit(lambda p: res(p, U1, Z1, X01)), (p0,)),
        "jacfwd": (jax.jit(jax.jacfwd(lambda p: res(p, U1, Z1, X01))), (p0,)),
        "closed_jacobian": (closed_form("jacobian"), (pt, px)),
        "closed_vjp": (closed_form("vjp"), (pt, px)),
    }
    a = np.concatenate(fns["closed_jacobian"][0](pt, px)[1:], axis=1)
    b = np.concatenate(fns["closed_vjp"][0](pt, px)[1:], axis=1)
    assert np.allclose(a, b, rtol=1e-8, atol=1e-12 * float(np.max(np.abs(a)))), "strategies"
    calls = {name: (lambda fn=fn, args=args: fn(*args)) for name, (fn, args) in fns.items()}
    out = interleaved(calls, repeats, min_sample_s=0.0, warmup=1)
    out["n_columns"] = int(pt.shape[0] + px.shape[0])
    out["auto"] = sensitivity_strategy(
        "auto", 1, int(x0.shape[0]), out["n_columns"], int(u.shape[0]), x0.dtype.itemsize
    )
    out["T"] = int(pb.T)
    out["n_x"] = int(pb.n_x)
    return out
