import jax
import jax.numpy as jnp
import numpy as np

import oneshot_jax as oj

jax.config.update("jax_enable_x64", True)  # identification runs in float64


def euler(w, M, theta):  # the paper's satellite: I w' = M - w x (I w), I diagonal
    inertia = theta["I"]
    return (M - jnp.cross(w, inertia * w)) / inertia


model = oj.Model.from_ode(euler, dt=0.1)  # RK4 over each sample interval

rng = np.random.default_rng(0)
M = 1e-5 + 1e-7 * rng.standard_normal((50, 3))  # known torques
_, w = oj.simulate(
    model, {"I": np.array([0.0403, 0.0404, 0.0080])}, np.array([9.915e-6, -1.102e-3, 1.3179e-5]), M
)
z = w + 1e-4 * rng.standard_normal(w.shape)  # measured angular velocities

theta0 = {"I": np.array([0.05, 0.03, 0.01])}
result = oj.fit(model, theta0, z[0], M, z, constraints=oj.constraints.positive())
print(result)  # stop reason, estimates with standard errors and 95 % intervals, FIT%
