"""Why a hybrid fit needs the statistical stopping test (`RESULTS.statistically_converged`).

A pendulum whose damping is an MLP(8) of the rate (the physics: w0sq and an input gain g;
RK4, dt = 0.05 s, T = 400, noise 0.01 rad), started near the truth. It prints:

1. Levenberg-Marquardt with the statistical test off (`stol=0`) for `--steps` steps: the
   first-order measure (the largest cosine of MINPACK's gtol test) it ends at, and the
   physical parameters with their marginal standard errors.
2. At that point, from the autodiff Jacobian: the numerical rank of J (the covariance's
   cutoff, sqrt(1e3 eps) of the largest Jacobi-scaled singular value), the Gauss-Newton
   step's predicted decrease ||P_J r||^2 in units of sigma^2 = C / (R - rank) and its size
   in standard errors, and the actual change of the loss along a fraction of that step.
3. The same fit with the statistical test at several `stol` (0.01 is the default): its
   stop, the step it stopped at, the physical parameters and standard errors, and how
   far (in standard errors) they are from those of the long run.

The numbers quoted in the module docstring of `oneshot_jax._optimality` come from
`python benchmarks/hybrid_stopping.py --steps 3000`.
"""

import argparse

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

import oneshot_jax as oj
from oneshot_jax.residual import MLP

jax.config.update("jax_enable_x64", True)
DT, T = 0.05, 400


def truth_rhs(x, u, p):
    q, v = x
    damping = 0.5 * v + 1.0 * jnp.tanh(3 * v)
    return jnp.stack([v, -p["w0sq"] * jnp.sin(q) - damping + p["g"] * u[0]])


def hybrid_rhs(x, u, th):
    q, v = x
    return jnp.stack([v, -th["w0sq"] * jnp.sin(q) + th["r"](x[1:])[0] + th["g"] * u[0]])


def observe(x, u, p):
    return x[:1]


def data():
    rng = np.random.default_rng(0)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.5, 3.0, 6.0))[:, None]
    truth = oj.Model.from_ode(truth_rhs, DT, observe=observe)
    x, z = oj.simulate(truth, {"w0sq": 9.0, "g": 1.0}, np.zeros(2), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal((T, 1))
    return u, z, float(np.std(np.asarray(x)[:, 1]))


def jacobian(model, result, u, z):
    """Residuals and their Jacobian in (theta's floating leaves, x0) by jax.jacfwd."""
    params, static = eqx.partition(result.theta, eqx.is_inexact_array)
    flat, unravel = ravel_pytree(params)
    n = flat.size

    def residuals(v):
        _, zhat = oj.simulate(model, eqx.combine(unravel(v[:n]), static), v[n:], u)
        return (zhat - z).ravel()

    v = jnp.concatenate([flat, jnp.asarray(result.x0)])
    return residuals, np.asarray(v), np.asarray(residuals(v)), np.asarray(jax.jacfwd(residuals)(v))


def physics(result):
    return {k: (float(result.theta[k]), float(result.std[k])) for k in ("w0sq", "g")}


def main(steps):
    u, z, rate_std = data()
    model = oj.Model.from_ode(hybrid_rhs, DT, observe=observe)
    net = MLP(1, 1, (8,), key=jax.random.PRNGKey(0), input_scale=rate_std)
    theta0 = {"w0sq": 8.7, "g": 0.9, "r": net}
    x0 = np.zeros(2)

    long = oj.fit(model, theta0, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=steps, stol=0.0))
    print(
        f"1. LM, stol=0, {long.num_steps} steps: {long.status}, "
        f"first-order measure {long.stop_info['first_order']:.2g}"
    )
    for k, (v, s) in physics(long).items():
        print(f"   {k} = {v:.4f} +- {s:.4f}")

    residuals, v, r, J = jacobian(model, long, u, z)
    d = np.linalg.norm(J, axis=0)
    d = np.where(d > 0, d, 1.0)
    U, S, Vt = np.linalg.svd(J / d, full_matrices=False)
    keep = S > np.sqrt(1e3 * np.finfo(float).eps) * S[0]
    rank = int(keep.sum())
    sigma2 = (r @ r) / (r.size - rank)
    c = U[:, keep].T @ r
    gn = -(Vt[keep].T @ (c / S[keep])) / d
    print(
        f"2. {J.shape[1]} free variables, rank {rank}; Gauss-Newton step: predicted "
        f"decrease {np.sum(c**2) / sigma2:.3g} sigma^2 ({np.sqrt(np.sum(c**2) / sigma2):.2g} "
        "standard errors)"
    )
    for alpha in (1.0, 1e-1, 1e-2, 1e-3):
        rn = np.asarray(residuals(jnp.asarray(v + alpha * gn)))
        print(
            f"   {alpha:g} of the step: loss change {(rn @ rn - r @ r) / sigma2:+.3g} sigma^2 "
            f"(predicted {-(2 * alpha - alpha**2) * np.sum(c**2) / sigma2:+.3g})"
        )

    ref = physics(long)
    for stol in (0.01, 0.03, 0.05, 0.1):
        short = oj.fit(
            model, theta0, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=steps, stol=stol)
        )
        print(
            f"3. LM, stol={stol:g}: {short.status} at step {short.num_steps}, last step "
            f"{short.stop_info['standard_errors']:.2g} standard errors"
        )
        for k, (val, s) in physics(short).items():
            print(
                f"   {k} = {val:.4f} +- {s:.4f}, {(ref[k][0] - val) / s:+.2f} standard errors "
                "from the long run"
            )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=3000)
    main(parser.parse_args().steps)
