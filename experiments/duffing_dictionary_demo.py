"""Sparse dictionary recovery of a missing cubic stiffness (demo, not a test).

The true system is a Duffing oscillator q'' + c q' + k q + eps q^3 = u, observed through q
with white noise at 40 dB SNR. The physical model knows c q' + k q but not the cubic term;
a `Dictionary` of 16 candidate monomials in (q, v, u) of degree 2 and 3 stands in for it.

- Reference: Levenberg-Marquardt (`oneshot_jax.fit`) on every candidate from the
  physical start, with and without a `penalties.state_box` barrier.
- A: Adam, no penalty: `oneshot_jax.value_and_grad` in a hand-written loop, theta holding
  the physical parameters and the Dictionary module (arrays split off with eqx.partition,
  which `fit` will do itself). B: LM on every candidate from there.
- C (selection): `sparsity.proximal_adam(eta, sparsity.l1(lam, where=<coefficients>))`
  from B, with the lasso on the rms-normalised coefficients, or the adaptive lasso
  (weights 1 / |w_B|, done by dividing the Dictionary's `scale` by |w_B|). D (debiasing):
  LM on the physical parameters and the selected coefficients only (the zeros fixed).

Prints the support, the cubic coefficient's error and the validation RMSE against the
noise level, for a few penalty strengths. Run:

    PYTHONPATH=. python experiments/duffing_dictionary_demo.py
"""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import oneshot_jax as oj
from oneshot_jax import penalties, sparsity
from oneshot_jax.residual import Dictionary, Features

jax.config.update("jax_enable_x64", True)

DT, T = 0.05, 2000
TRUE = {"c": 0.3, "k": 1.0, "eps": 0.8}
SNR_DB = 40.0


def true_rhs(x, u, p):
    q, v = x
    return jnp.stack([v, u[0] - p["c"] * v - p["k"] * q - p["eps"] * q**3])


def hybrid_rhs(x, u, theta):
    q, v = x
    r = theta["r"](x, u)
    return jnp.stack([v, u[0] - theta["c"] * v - theta["k"] * q + r[0]])


def observe_q(x, u, theta):
    del u, theta
    return x[:1]


def multisine(seed, T):
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    freqs = np.linspace(0.05, 0.6, 12) * 2 * np.pi
    phases = rng.uniform(0, 2 * np.pi, freqs.size)
    u = np.sum(np.sin(np.outer(t, freqs) + phases), axis=1)
    return jnp.asarray(1.5 * u / np.std(u))[:, None]


def make_data(seed):
    u = multisine(seed, T)
    x0 = jnp.array([0.5, 0.0])
    model = oj.Model.from_ode(true_rhs, DT, observe=observe_q)
    _, z = oj.simulate(model, TRUE, x0, u)
    sigma = float(jnp.sqrt(jnp.mean(z**2))) * 10 ** (-SNR_DB / 20)
    noise = sigma * np.random.default_rng(seed + 100).standard_normal(z.shape)
    return u, z + noise, x0, sigma


def main():
    u, z, x0_true, sigma = make_data(0)
    u_val, z_val, x0_val, _ = make_data(1)
    feats = Features(2, 1, degree=3, x_names=("q", "v"), u_names=("u",), exclude=("q", "v", "u"))
    phys0 = {"c": jnp.asarray(0.2), "k": jnp.asarray(1.3)}
    x0_guess = jnp.array([0.4, 0.1])
    j3 = feats.names.index("q^3")
    print(f"noise sigma = {sigma:.4g}, {len(feats)} candidates: {', '.join(feats.names)}")

    def with_coef(d, coef):
        return eqx.tree_at(lambda d: d.coef, d, coef)

    def flat_model(d):
        """The hybrid with theta = {"c", "k", "coef"} (arrays only), for `oneshot_jax.fit`."""

        def rhs(x, u, p):
            return hybrid_rhs(x, u, {"c": p["c"], "k": p["k"], "r": with_coef(d, p["coef"])})

        return oj.Model.from_ode(rhs, DT, observe=observe_q)

    # Per-term scales from the initial physical model's simulated states (v is not measured).
    xs0, _ = oj.simulate(
        flat_model(Dictionary(feats, 1)), {**phys0, "coef": jnp.zeros((16, 1))}, x0_true, u
    )
    dic = Dictionary(feats, 1, out_names=("dv",), scale=feats.rms(xs0, u))

    def report(label, d, th, t):
        final = with_coef(d, th["coef"])
        phys_coef = np.asarray(final.coefficients)[:, 0]
        err = abs(phys_coef[j3] - (-TRUE["eps"])) / TRUE["eps"]
        wrong = [n for n, c in zip(feats.names, phys_coef) if c != 0 and n != "q^3"]
        _, z_hat = oj.simulate(flat_model(d), th, x0_val, u_val)
        rmse = float(jnp.sqrt(jnp.mean((z_hat - z_val) ** 2)))
        print(f"  {label} ({t:.1f} s): " + final.equations())
        print(
            f"    c = {float(th['c']):.4f} (true 0.3), k = {float(th['k']):.4f} (true 1.0); "
            f"q^3 coefficient error {100 * err:.2f} %; {len(wrong)} wrong non-zero terms; "
            f"validation RMSE {rmse:.4g} = {rmse / sigma:.3f} x sigma"
        )

    def prox_adam(d, th, x0, lam, lr0, n_steps):
        """n_steps of proximal Adam (L1 on the coefficients) with theta holding the module."""
        theta = {"c": th["c"], "k": th["k"], "r": with_coef(d, th["coef"])}
        params, static = eqx.partition(theta, eqx.is_inexact_array)
        model = oj.Model.from_ode(
            lambda x, u, p: hybrid_rhs(x, u, eqx.combine(p, static)), DT, observe=observe_q
        )
        lr = optax.cosine_decay_schedule(lr0, n_steps, alpha=1e-2)
        where = sparsity.mask(lambda p: p["theta"]["r"].coef)
        tx = sparsity.proximal_adam(lr, sparsity.l1(lam, where=where))
        var = {"theta": params, "x0": x0}
        state = tx.init(var)

        @eqx.filter_jit
        def step(var, state):
            C, (g_theta, g_x0) = oj.value_and_grad(model, var["theta"], var["x0"], u, z)
            upd, state = tx.update({"theta": g_theta, "x0": g_x0}, state, var)
            return optax.apply_updates(var, upd), state, C

        for _ in range(n_steps):
            var, state, C = step(var, state)
        out = eqx.combine(var["theta"], static)
        return {"c": out["c"], "k": out["k"], "coef": out["r"].coef}, var["x0"], float(C)

    def lm(d, th, x0, **kw):
        return oj.fit(flat_model(d), u, z, th, x0, solver="levenberg_marquardt", **kw)

    flat0 = {**phys0, "coef": dic.coef}
    zmax = float(jnp.max(jnp.abs(z)))
    barrier = penalties.state_box(
        lower=[-2 * zmax, -np.inf], upper=[2 * zmax, np.inf], width=0.1 * zmax
    )
    for label, kw in [("no barrier", {}), ("state_box barrier on q", {"penalty": barrier})]:
        t0 = time.perf_counter()
        res0 = lm(dic, flat0, x0_guess, **kw)
        print(
            f"\nLM on all {len(feats)} candidates from the physical start, {label}: "
            f"C = {float(res0.loss):.4g}"
        )
        report("LM", dic, res0.theta, time.perf_counter() - t0)

    t0 = time.perf_counter()
    th_a, x0_a, C_a = prox_adam(dic, flat0, x0_guess, 0.0, 2e-2, 2000)
    print(f"\nA: Adam (no penalty), 2000 steps from the physical start: C = {C_a:.4g}")
    report("Adam", dic, th_a, time.perf_counter() - t0)
    t0 = time.perf_counter()
    res_b = lm(dic, th_a, x0_a)
    print(f"\nB: LM on all candidates from A: C = {float(res_b.loss):.4g}")
    report("LM", dic, res_b.theta, time.perf_counter() - t0)

    # The adaptive lasso: weights 1 / |w_B| on the normalised coefficients are the plain
    # lasso on a dictionary whose scales are divided by |w_B|.
    w_b = np.asarray(res_b.theta["coef"])[:, 0]
    dic_ad = Dictionary(feats, 1, out_names=("dv",), scale=np.asarray(dic.scale) / np.abs(w_b))
    start_ad = {**res_b.theta, "coef": jnp.asarray(np.sign(w_b))[:, None]}
    runs = [("lasso", dic, res_b.theta, 1e-3)]
    runs += [("adaptive lasso", dic_ad, start_ad, lam) for lam in (1e-4, 1e-3)]
    for name, d, start, lam in runs:
        t0 = time.perf_counter()
        th_c, x0_c, C_c = prox_adam(d, start, res_b.x0, lam, 1e-3, 2000)
        print(f"\nC: {name}, lambda = {lam:g}, 2000 proximal Adam steps from B: C = {C_c:.4g}")
        report("proximal Adam", d, th_c, time.perf_counter() - t0)
        fixed = {"c": False, "k": False, "coef": np.asarray(th_c["coef"]) == 0}
        t0 = time.perf_counter()
        res = lm(d, th_c, x0_c, fixed=fixed)
        report("D: LM on the support", d, res.theta, time.perf_counter() - t0)

    # Reference: the physical model alone (no residual), fitted by LM.
    phys_model = oj.Model.from_ode(
        lambda x, u, p: hybrid_rhs(x, u, {**p, "r": lambda x, u: jnp.zeros(1)}),
        DT,
        observe=observe_q,
    )
    res = oj.fit(phys_model, u, z, phys0, x0_guess, solver="levenberg_marquardt")
    _, z_hat = oj.simulate(phys_model, res.theta, x0_val, u_val)
    rmse = float(jnp.sqrt(jnp.mean((z_hat - z_val) ** 2)))
    print(f"\nphysical model only (LM): validation RMSE {rmse:.4g} = {rmse / sigma:.2f} x sigma")


if __name__ == "__main__":
    main()
