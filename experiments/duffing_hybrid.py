"""Hybrid models on a synthetic Duffing oscillator: a sparse dictionary recovers the
missing cubic stiffness, and a neural residual closes the gap to the noise level.

The true system is q'' + c q' + k q + eps q^3 = u (c = 0.3, k = 1, eps = 0.8), sampled at
dt = 0.05 s under a multisine input and observed through q with white noise at an SNR of
40 dB. The physical model knows c q' + k q but not the cubic term; a learned residual r
is added to the acceleration:

    q'' = u - c q' - k q + r(q, q', u).

Both residuals are trained with `oneshot_jax.fit` only, in stages that each start where
the last stopped:

- **Dictionary** (16 candidate monomials of degree 2 and 3 in q, v = q', u):
  1. every candidate: Adam (cosine-decayed rate) then Levenberg-Marquardt;
  2. selection: proximal Adam with the adaptive lasso (`sparsity.l1` in
     `regulariser=`; weights 1 / |w| from stage 1, applied through the dictionary's
     `scale`), which sets the wrong candidates to exactly zero;
  3. debiasing: Levenberg-Marquardt on the surviving terms, the zeros held by
     `fixed=sparsity.fixed_zeros(...)`.
- **MLP** (`residual.MLP` restoring force r(q, v), zero at the start), trained on three
  records (seeds 0, 2, 4: a network only learns the states it has seen):
  1. the physical parameters alone (`fixed` holds the network);
  2. jointly: Adam, then Levenberg-Marquardt.

Validation uses three other records (seeds 1, 3, 5: other multisines, other noise),
simulated from their true initial states. Prints the support, the cubic coefficient's
error, and the validation RMSE against each record's noise level sigma. Run (several
minutes):

    python experiments/duffing_hybrid.py

`tests/test_hybrid.py` runs the same pipelines on shorter records.
"""

import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import oneshot_jax as oj  # noqa: E402
from oneshot_jax import sparsity  # noqa: E402
from oneshot_jax.residual import MLP, Dictionary, Features  # noqa: E402

DT = 0.05
TRUE = {"c": 0.3, "k": 1.0, "eps": 0.8}
PHYSICAL_START = {"c": 0.2, "k": 1.3}
X0_TRUE = (0.5, 0.0)
X0_GUESS = (0.4, 0.1)
CUBIC = "q^3"


def true_rhs(x, u, p):
    """The true Duffing oscillator, x = (q, v)."""
    q, v = x
    return jnp.stack([v, u[0] - p["c"] * v - p["k"] * q - p["eps"] * q**3])


def hybrid_rhs(x, u, theta):
    """The physics without the cubic term, plus the residual theta["r"]: a `Dictionary` of
    terms in (q, v, u), or an `MLP` restoring force r(q, v) (the input enters the physics
    linearly)."""
    q, v = x
    res = theta["r"]
    r = res(x) if isinstance(res, MLP) else res(x, u)
    return jnp.stack([v, u[0] - theta["c"] * v - theta["k"] * q + r[0]])


def observe_q(x, u, theta):
    del u, theta
    return x[:1]


MODEL = oj.Model.from_ode(hybrid_rhs, DT, observe=observe_q)


def multisine(seed, T, std=1.5):
    """12 sines between 0.05 and 0.6 Hz with random phases, scaled to `std`."""
    rng = np.random.default_rng(seed)
    t = DT * np.arange(T)
    freqs = np.linspace(0.05, 0.6, 12) * 2 * np.pi
    phases = rng.uniform(0, 2 * np.pi, freqs.size)
    u = np.sum(np.sin(np.outer(t, freqs) + phases), axis=1)
    return std * u[:, None] / np.std(u)


def make_data(seed, T, snr_db=40.0, std=1.5):
    """(u, z, x0, sigma): one record of the true system under `multisine(seed, T, std)`
    with white noise on q at the given SNR (sigma = rms(q) 10^(-snr/20))."""
    u = multisine(seed, T, std)
    x0 = np.asarray(X0_TRUE)
    _, z = oj.simulate(oj.Model.from_ode(true_rhs, DT, observe=observe_q), TRUE, x0, u)
    z = np.asarray(z)
    sigma = float(np.sqrt(np.mean(z**2))) * 10 ** (-snr_db / 20)
    noise = sigma * np.random.default_rng(seed + 100).standard_normal(z.shape)
    return u, z + noise, x0, sigma


def features():
    """The 16 candidates: monomials of degree 2 and 3 in (q, v, u)."""
    return Features(2, 1, degree=3, x_names=("q", "v"), u_names=("u",), exclude=("q", "v", "u"))


def physical_states(u):
    """States (T, 2) of the starting physical model (no residual), for feature scales;
    for records u (N, T, 1), all their states (N T, 2)."""
    theta = {**PHYSICAL_START, "r": Dictionary(features(), 1)}
    u = np.asarray(u)
    x0 = np.broadcast_to(np.asarray(X0_TRUE), (*u.shape[:-2], 2))
    xs, _ = oj.simulate(MODEL, theta, x0, u)
    return np.asarray(xs).reshape(-1, 2)


COEF = sparsity.mask(lambda theta: theta["r"].coef)
VALIDATION_SEEDS = (1, 3, 5)
MLP_SEEDS = (0, 2, 4)


def select_terms(u, z, *, adam_steps=2000, prox_steps=2000, lam=1e-3, prox_lr=5e-3, progress=False):
    """The staged sparse-dictionary fit. Returns the stage results (all, selected, refit)."""
    feats = features()
    rms = feats.rms(physical_states(u), u)
    theta0 = {**PHYSICAL_START, "r": Dictionary(feats, 1, out_names=("dv",), scale=rms)}
    lr = optax.cosine_decay_schedule(2e-2, adam_steps, alpha=1e-2)
    every = oj.fit(
        MODEL,
        theta0,
        np.asarray(X0_GUESS),
        u,
        z,
        solver=[oj.Adam(lr, lr, max_steps=adam_steps), oj.LevenbergMarquardt()],
        progress=progress,
    )
    # Adaptive lasso: the penalty lam sum_i |w_i| / |w_i^every| on the normalised
    # coefficients is the plain lasso on a dictionary whose scales are divided by |w^every|.
    w = np.asarray(every.theta["r"].coef)[:, 0]
    adaptive = Dictionary(
        feats, 1, out_names=("dv",), scale=rms / np.abs(w), coef=np.sign(w)[:, None]
    )
    lr = optax.cosine_decay_schedule(prox_lr, prox_steps, alpha=1e-2)
    selected = oj.fit(
        MODEL,
        {**every.theta, "r": adaptive},
        every.x0,
        u,
        z,
        solver=oj.Adam(lr, 1e-4, max_steps=prox_steps),
        regulariser=sparsity.l1(lam, where=COEF),
        progress=progress,
    )
    refit = oj.fit(
        MODEL,
        selected.theta,
        selected.x0,
        u,
        z,
        fixed=sparsity.fixed_zeros(selected.theta, where=COEF),
        progress=progress,
    )
    return every, selected, refit


def train_mlp(u, z, *, widths=(8, 8), adam_steps=3000, lm_steps=100, key=0, progress=False):
    """The staged neural-residual fit on one record (u (T, 1), z (T, 1)) or several
    (u (N, T, 1), z (N, T, 1), each with its own x0). Returns the stage results
    (physics, joint)."""
    feats = physical_states(u)
    x0 = np.broadcast_to(np.asarray(X0_GUESS), (*np.shape(u)[:-2], 2))
    net = MLP(
        2,
        1,
        widths,
        key=jax.random.PRNGKey(key),
        input_offset=feats.mean(0),
        input_scale=feats.std(0),
    )
    theta0 = {**PHYSICAL_START, "r": net}
    physics = oj.fit(
        MODEL,
        theta0,
        x0,
        u,
        z,
        fixed={"c": False, "k": False, "r": True},
        progress=progress,
    )
    lr = optax.cosine_decay_schedule(1e-2, adam_steps, alpha=1e-2)
    joint = oj.fit(
        MODEL,
        physics.theta,
        physics.x0,
        u,
        z,
        solver=[
            oj.Adam(lr, 1e-3, max_steps=adam_steps),
            oj.LevenbergMarquardt(max_steps=lm_steps),
        ],
        progress=progress,
    )
    return physics, joint


def validation_rmse(theta, u, z, x0):
    """RMSE of the simulated output against the measured one, from the true x0."""
    _, zhat = oj.simulate(MODEL, theta, x0, u)
    return float(np.sqrt(np.mean((np.asarray(zhat) - z) ** 2)))


def cubic_report(theta):
    """(relative error of the q^3 coefficient, names of the wrong non-zero terms)."""
    d = theta["r"]
    coef = np.asarray(d.coefficients)[:, 0]
    names = d.names
    err = abs(coef[names.index(CUBIC)] + TRUE["eps"]) / TRUE["eps"]
    wrong = [n for n, c in zip(names, coef) if c != 0 and n != CUBIC]
    return float(err), wrong


def main(T=2000):
    u, z, _, sigma = make_data(0, T)
    validation = [make_data(seed, T) for seed in VALIDATION_SEEDS]
    u_val, z_val, x0_val, sigma_val = validation[0]

    def rmses(theta):
        return [validation_rmse(theta, uv, zv, x0v) / sv for uv, zv, x0v, sv in validation]

    def fmt(values):
        return ", ".join(f"{v:.3f}" for v in values)

    print(
        f"Duffing, T = {T}, SNR 40 dB: noise sigma = {sigma:.4g}; validation RMSE in units "
        f"of each validation record's sigma, records (seeds) {VALIDATION_SEEDS}"
    )

    t0 = time.perf_counter()
    phys = oj.fit(
        MODEL,
        {**PHYSICAL_START, "r": Dictionary(features(), 1)},
        np.asarray(X0_GUESS),
        u,
        z,
        fixed={"c": False, "k": False, "r": True},
    )
    print(
        f"\nphysical model alone (LM, {time.perf_counter() - t0:.1f} s): c = "
        f"{float(phys.theta['c']):.4f}, k = {float(phys.theta['k']):.4f}; validation RMSE "
        f"[{fmt(rmses(phys.theta))}] sigma"
    )

    t0 = time.perf_counter()
    every, selected, refit = select_terms(u, z)
    wall = time.perf_counter() - t0
    print(
        f"\nsparse dictionary, trained on record 0 ({len(features())} candidates, {wall:.1f} s "
        "for the 3 stages):"
    )
    for label, res in (("all terms", every), ("selected", selected), ("refit", refit)):
        err, wrong = cubic_report(res.theta)
        print(
            f"  {label:9s}: {res.theta['r'].equations()}\n"
            f"             c = {float(res.theta['c']):.4f}, k = {float(res.theta['k']):.4f}; "
            f"q^3 coefficient error {100 * err:.3f} %; {len(wrong)} wrong non-zero terms; "
            f"objective {float(res.loss):.4g}; validation RMSE [{fmt(rmses(res.theta))}] sigma"
        )

    # The network needs the states it will meet: three training records.
    records = [make_data(seed, T) for seed in MLP_SEEDS]
    u_n = np.stack([r[0] for r in records])
    z_n = np.stack([r[1] for r in records])
    sigma2 = float(np.mean([r[3] ** 2 for r in records]))
    t0 = time.perf_counter()
    physics, joint = train_mlp(u_n, z_n)
    wall = time.perf_counter() - t0
    n = oj.residual.count_parameters(joint.theta)
    print(
        f"\nMLP restoring force r(q, v) ({n} parameters with c, k), trained on records "
        f"{MLP_SEEDS} ({wall:.1f} s for the 2 stages); noise variance {sigma2:.4g}:"
    )
    for label, res in (("physics", physics), ("joint", joint)):
        print(
            f"  {label:7s}: c = {float(res.theta['c']):.4f}, k = {float(res.theta['k']):.4f}; "
            f"training loss {float(res.loss):.4g} ({res.status}); validation "
            f"RMSE [{fmt(rmses(res.theta))}] sigma"
        )


if __name__ == "__main__":
    main()
