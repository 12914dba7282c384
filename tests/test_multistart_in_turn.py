"""A multistart's starts in turn (`lax.map`, each start stopping on its own tests; the
default on a CPU) and side by side (vmapped, every start stepping until the last one
stops) give the same fit.

The case: a damped rotation by w whose multi-step loss over w has local minima, from
starts that need different numbers of steps and stop for different reasons, through a
sequence of two solvers, with and without held-out records. Side by side, a start that
has stopped is frozen while the others step; in turn, it is simply done: the per-start
losses, stop reasons and parameters, the best start and its history must agree, to
rounding (the batched arithmetic rounds differently; some starts on this periodic
landscape amplify that into another basin, these ones agree to 1e-9). In turn, the best
start's history is thinned by its own step count only, so it holds every row of the
side-by-side one. A wrong stacking of the in-turn outputs (the history's rows and
starts swapped, a start's steps or history taken from another) changes one of them.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj
from oneshot_jax.internal import iterate_module

T = 60
W_TRUE, RHO_TRUE = 0.3, 0.97
W_STARTS = np.array([-0.8, 0.25, 1.2, -1.5])


def step(x, u, theta):
    w, rho = theta["w"], theta["rho"]
    c, s = jnp.cos(w), jnp.sin(w)
    return rho * jnp.stack([c * x[0] - s * x[1], s * x[0] + c * x[1]]) + u[0] * jnp.array(
        [1.0, 0.0]
    )


MODEL = oj.Model(step)


def _data(seed, n=T):
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 1))
    x0 = np.array([1.0, 0.0])
    _, z = oj.simulate(MODEL, {"w": W_TRUE, "rho": RHO_TRUE}, x0, u)
    return x0, u, np.asarray(z) + 0.01 * rng.standard_normal((n, 2))


def _fit(monkeypatch, in_turn, validation):
    monkeypatch.setattr(iterate_module, "STARTS_IN_TURN", in_turn)
    x0, u, z = _data(0)
    kwargs = {}
    if validation:
        _, u_val, z_val = _data(1, 40)
        kwargs["validation"] = oj.Validation(u_val, z_val, n=5)
    return oj.fit(
        MODEL,
        {"w": -0.8, "rho": 0.9},
        x0,
        u,
        z,
        solver=[oj.Adam(1e-2, max_steps=7), oj.LevenbergMarquardt(max_steps=15, gtol=1e-6)],
        multistart={"w": W_STARTS},
        history=8,
        **kwargs,
    )


@pytest.mark.parametrize("validation", [False, True], ids=["plain", "validation"])
def test_starts_in_turn_equal_starts_side_by_side(monkeypatch, validation):
    side = _fit(monkeypatch, False, validation)
    turn = _fit(monkeypatch, True, validation)
    # The case is one where the paths could differ: the starts stop for different
    # reasons (at different steps), and the best start is not the first.
    assert len(set(side.starts.stop_reason)) >= 2
    assert side.best != 0
    assert turn.starts.stop_reason == side.starts.stop_reason
    assert turn.best == side.best
    np.testing.assert_allclose(turn.starts.loss, side.starts.loss, rtol=1e-7)
    for name in ("w", "rho"):
        np.testing.assert_allclose(
            turn.starts.theta[name], side.starts.theta[name], rtol=1e-7, atol=1e-12
        )
        np.testing.assert_allclose(turn.theta[name], side.theta[name], rtol=1e-7)
    np.testing.assert_allclose(turn.x0, side.x0, rtol=1e-7, atol=1e-9)
    assert turn.status == side.status
    # The best start's history: side by side, the rows are thinned by the step count of
    # the longest start (the stride is shared); in turn, by its own. So its rows in turn
    # hold every row side by side, with the same values, and its last row is the same.
    h_side, h_turn = side.history, turn.history
    turn_rows = {(int(g), int(k)): i for i, (g, k) in enumerate(zip(h_turn.stage, h_turn.step))}
    rows = [turn_rows[(int(g), int(k))] for g, k in zip(h_side.stage, h_side.step)]
    assert len(rows) < len(h_turn.step)  # (side by side thinned more: the case differs)
    np.testing.assert_allclose(h_turn.loss[rows], h_side.loss, rtol=1e-7)
    # (near the optimum the gradient is a cancellation: equal to rounding of its size)
    g_atol = 1e-9 * np.max(h_side.grad_norm)
    np.testing.assert_allclose(h_turn.grad_norm[rows], h_side.grad_norm, rtol=1e-7, atol=g_atol)
    np.testing.assert_allclose(h_turn.theta["w"][rows], h_side.theta["w"], rtol=1e-7)
    assert rows[-1] == len(h_turn.step) - 1
    if validation:
        np.testing.assert_allclose(h_turn.validation[rows], h_side.validation, rtol=1e-7)
    else:
        assert h_turn.validation is None and h_side.validation is None


def test_side_by_side_levenberg_marquardt_takes_a_single_fits_steps(monkeypatch):
    """Levenberg-Marquardt follows every rejected step with a projected-gradient step.
    It used to do so only where its test of whether the projection clipped the step fired,
    a test that compared (theta + h) - theta with h: round-off made it fire or not
    depending on how XLA compiled the arithmetic (vmapped or not), without any bound. Two
    identical starts side by side then took other steps than a single fit (on this
    hybrid, whose first steps are rejected); now every path takes the same steps."""
    from oneshot_jax.residual import MLP

    def hybrid(x, u, theta):
        return step(x, u, theta["phys"]) + 0.1 * theta["r"](jnp.concatenate([x, u]))

    model = oj.Model(hybrid)
    x0, u, z = _data(0)
    net = MLP(3, 2, (6,), key=jax.random.PRNGKey(0))
    theta0 = {"phys": {"w": -1.5, "rho": 0.9}, "r": net}
    warm = oj.fit(model, theta0, x0, u, z, solver=oj.Adam(1e-2, max_steps=20, gtol=0.0))
    lm = oj.LevenbergMarquardt(max_steps=6)
    single = oj.fit(model, warm.theta, warm.x0, u, z, solver=lm)
    for in_turn in (False, True):
        monkeypatch.setattr(iterate_module, "STARTS_IN_TURN", in_turn)
        both = oj.fit(
            model, warm.theta, np.stack([warm.x0, warm.x0]), u, z, solver=lm, multistart={}
        )
        np.testing.assert_array_equal(both.history.step, single.history.step)
        np.testing.assert_allclose(both.history.loss, single.history.loss, rtol=1e-9)


@pytest.mark.parametrize("in_turn", [True, False], ids=["in turn", "side by side"])
def test_progress_bar_ends_at_the_least_loss_over_the_starts(monkeypatch, capsys, in_turn):
    """The progress bar shows the least loss over the starts. In turn, the start running
    last is not the best one here: the bar used to end on that start's loss. Its total:
    every start's steps in turn, the shared steps side by side."""
    monkeypatch.setattr(iterate_module, "STARTS_IN_TURN", in_turn)
    x0, u, z = _data(0)
    starts = np.array([0.25, -1.5, 1.2])
    r = oj.fit(
        MODEL,
        {"w": 0.25, "rho": 0.9},
        x0,
        u,
        z,
        solver=oj.Adam(1e-2, max_steps=30, gtol=0.0),
        multistart={"w": starts},
        progress=oj.TqdmProgress(1),
    )
    assert r.best == 0 and r.starts.loss[-1] > 10 * r.loss  # (the last start is not the best)
    err = capsys.readouterr().err
    assert f"/{30 * (3 if in_turn else 1)}" in err
    shown = err.rsplit("loss ", 1)[1].split()[0].rstrip("]")
    assert shown == f"{float(np.min(r.starts.loss)):.6e}", err[-300:]
