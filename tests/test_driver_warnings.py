"""The warnings of the fits that the drivers run point at the user's line, as `fit`'s do."""

import inspect
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj


def _step(x, u, th):
    # e has no effect (a parameter the data cannot determine: `fit` warns), r is the
    # learned term of the hybrid drivers; the model warns too, when it is traced
    warnings.warn("a warning of the model's own", UserWarning)
    return th["a"] * x + th["b"] * u + th["r"][0] * jnp.tanh(x) + th["r"][1] * u**3 + 0.0 * th["e"]


_OWN_LINE = next(
    i
    for i, line in enumerate(inspect.getsourcelines(_step)[0], inspect.getsourcelines(_step)[1])
    if "warnings.warn" in line
)


def _record():
    rng = np.random.default_rng(0)
    u = rng.standard_normal((120, 1))
    truth = {"a": 0.8, "b": 0.5, "r": np.array([0.1, 0.0]), "e": 0.0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (the model's own)
        _, z = oj.simulate(oj.Model(_step), truth, np.zeros(1), u)
    return u, np.asarray(z) + 0.01 * rng.standard_normal((120, 1))


THETA0 = {"a": 0.6, "b": 0.3, "r": np.array([0.05, 0.01]), "e": 0.2}
FEW = oj.LevenbergMarquardt(max_steps=20)


def _continuation(model, u, z):
    return oj.fit_continuation(model, THETA0, np.zeros(1), u, z, windows=(40,), solver=FEW)


def _basin(model, u, z):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = oj.fit(model, THETA0, np.zeros(1), u, z, solver=FEW)
    return oj.check_basin(r, u, z, window=40, solver=FEW)


def _physics_first(model, u, z):
    return oj.fit_physics_first(model, THETA0, np.zeros(1), u, z, learned="r", solver=FEW)


def _orthogonal(model, u, z):
    return oj.fit_orthogonal(model, THETA0, np.zeros(1), u, z, learned="r", rounds=1, solver=FEW)


@pytest.mark.parametrize(
    "driver",
    [_continuation, _basin, _physics_first, _orthogonal],
    ids=["fit_continuation", "check_basin", "fit_physics_first", "fit_orthogonal"],
)
def test_a_drivers_fit_warnings_point_at_its_caller(driver):
    """They pointed at the driver's own line in the library (`_identifiable.py`,
    `_continuation.py`), where a plain `fit` points at its caller's. A warning of the
    model keeps its own line (the first version moved every warning to the caller's)."""
    u, z = _record()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        driver(oj.Model(_step), u, z)
    about_e = [w for w in caught if "e" in str(w.message) and "null space" in str(w.message)]
    assert about_e, [str(w.message)[:120] for w in caught]
    assert {w.filename for w in caught} == {__file__}
    own = [w for w in caught if "of the model's own" in str(w.message)]
    assert own and {w.lineno for w in own} == {_OWN_LINE}
    assert _OWN_LINE not in {w.lineno for w in about_e}
