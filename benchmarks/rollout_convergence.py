"""How the parallel rollout converges on a strongly nonlinear oscillation, by chunk size.

The parallel path (`strategy="parallel"`, `oneshot_jax.ParallelInTime`) rolls a record out
by DEER Newton iterations from the constant guess x_k = x_0, then a damped (ELK) stage,
then the sequential loop where neither converges (`oneshot_jax._parallel._rollout`). On
the chain of `parallel.py` Newton converges in about 7 iterations. Here the Duffing
oscillator of `multistart.py` (q'' = u - c q' - k q - eps q^3, RK4, dt = 0.05, a multisine
scaled to a standard deviation of 1.5, |q| up to about 4), at the multistart's starts of
theta: (c, eps) = (0.25, 0.7) and k from 0.3 to 3. For each start and chunk size (`none`:
the whole record as one solve), the rollout's method (the last resort any chunk needed:
`newton`, `damped`, or `sequential`, the fallback), its Newton and damped iterations
summed over the chunks, and the largest difference from the sequential rollout (relative
to max|x|).
Newton stops early where its iterate overflows (it diverges), after 5 iterations without
a smaller residual, or at `max_iter` = 50; the damped stage at 50 iterations.

The iteration counts do not depend on the backend (up to round-off); on a GPU an
iteration costs a few dozen kernel launches, and the chunks are solved one after another.

Run: `python benchmarks/rollout_convergence.py` (`--T`, `--chunks`, `--starts S`).
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from multistart import MODEL, THETA0, make_data  # noqa: E402
from timing import conditions  # noqa: E402

from oneshot_jax.internal import METHOD_NAMES, newton_rollout, rollout  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--T", type=int, default=2000)
    parser.add_argument(
        "--chunks", nargs="+", default=["none", "500", "100"], help="chunk sizes ('none')"
    )
    parser.add_argument("--starts", type=int, default=8)
    args = parser.parse_args()
    u, _, x0 = make_data(args.T)
    u, x0 = jnp.asarray(u), jnp.asarray(x0)
    ks = np.geomspace(0.3, 3.0, args.starts)

    print(conditions(), "\n")
    print(f"T = {args.T}; Newton and damped iterations summed over the chunks.\n")
    print("| k | chunk | chunks | method | Newton | damped | max diff / max abs x |")
    print("|---|---|---|---|---|---|---|")
    for k in ks:
        theta = {**THETA0, "k": float(k)}
        ref = rollout(MODEL, theta, x0, u)
        for c in args.chunks:
            size = None if c == "none" else int(c)
            xs, info = newton_rollout(MODEL.step, theta, x0, u, chunk_size=size)
            diff = float(jnp.max(jnp.abs(xs - ref)) / jnp.max(jnp.abs(ref)))
            print(
                f"| {k:.3g} | {c} | {int(info.chunks)} | {METHOD_NAMES[int(info.method)]} | "
                f"{int(info.newton_iterations)} | {int(info.damped_iterations)} | {diff:.1e} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
