"""The paper's satellite (Section 4) in a few lines: a gradient check and a fit.

Run: `python experiments/quickstart.py`. The model is `oneshot_jax.examples.satellite`
(Euler's equations I w' = M - w x (I w), theta = {"I": diagonal of I}, RK4 at dt = 0.1 s).
Prints the agreement of the closed-form gradient with reverse-mode autodiff, then the
summary of a Gauss-Newton fit.
"""

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)  # identification runs in float64

import oneshot_jax as oj  # noqa: E402
from oneshot_jax.examples import satellite  # noqa: E402

model = satellite.model()  # RK4, zero-order-hold torque
theta = {"I": jnp.array(satellite.THETA_TRUE)}
w0 = jnp.array(satellite.W0)
key_m, key_e = jax.random.split(jax.random.PRNGKey(0))
M = 1e-5 + 1e-7 * jax.random.normal(key_m, (50, 3))  # known input torque
_, w = oj.simulate(model, theta, w0, M)
z = w + 1e-4 * jax.random.normal(key_e, w.shape)  # measured angular velocity

theta0 = {"I": jnp.array(satellite.THETA0)}
C, (g_theta, g_x0) = oj.value_and_grad(model, theta0, w0, M, z)
C_ad, (g_theta_ad, g_x0_ad) = jax.value_and_grad(
    lambda th, x0: oj.loss(model, th, x0, M, z), argnums=(0, 1)
)(theta0, w0)
rel = jnp.linalg.norm(g_theta["I"] - g_theta_ad["I"]) / jnp.linalg.norm(g_theta_ad["I"])
print(f"C = {C:.6e}; closed-form vs autodiff gradient, relative difference {rel:.1e}")

result = oj.fit(
    model, theta0, w0, M, z, solver="gauss_newton", constraints=oj.constraints.positive()
)
print(result)
