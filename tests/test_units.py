"""A fit's answer does not depend on the units the user picks.

A heated body losing heat by convection and radiation, C dT/dt = P - hA (T - Ta) -
kr (T^4 - Ta^4), in SI units (C about 1e4 J/K, kr about 5e-8 W/K^4: theta's entries 1e11
apart), in units of order 1 (C in kJ/K, kr in 1e-8 W/K^4) and in between (C in J/K, kr
in 1e-8 W/K^4). Gauss-Newton scales its steps by the Jacobian's columns: the same
estimates in the same steps in every unit system. Levenberg-Marquardt floors Marquardt's
diagonal at 1e-12 of its largest entry: the same steps while theta's entries lie within
about 1e6 of each other, more steps in SI units (the guide says so), the same estimates.
"""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

T, DT, TA = 500, 20.0, 293.15
TRUTH = {"C": 1e4, "hA": 10.0, "kr": 5e-8}


def _model(s_c, s_k):
    """The model with theta's C in units of 1/s_c J/K and kr in 1/s_k W/K^4."""

    def rhs(x, u, th):
        C, hA, kr = th["C"] / s_c, th["hA"], th["kr"] / s_k
        return jnp.array([(u[0] - hA * (x[0] - TA) - kr * (x[0] ** 4 - TA**4)) / C])

    return oj.Model.from_ode(rhs, dt=DT)


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(4)
    P = np.repeat(rng.uniform(0, 3000, T // 25), 25)[:, None]
    _, z = oj.simulate(_model(1.0, 1.0), TRUTH, np.array([300.0]), P)
    return P, np.asarray(z) + 0.05 * rng.standard_normal((T, 1))


@pytest.mark.parametrize(
    "solver, units",
    [
        ("gauss_newton", {"SI": (1.0, 1.0), "order 1": (1e-3, 1e8)}),
        ("levenberg_marquardt", {"J/K": (1.0, 1e8), "order 1": (1e-3, 1e8)}),
    ],
)
def test_least_squares_fits_do_not_depend_on_theta_s_units(data, solver, units):
    P, z = data
    fits = {}
    for name, (s_c, s_k) in units.items():
        theta0 = {"C": 2e4 * s_c, "hA": 5.0, "kr": 2e-8 * s_k}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = oj.fit(_model(s_c, s_k), theta0, z[0], P, z, solver=solver)
        assert r.success, (name, r.message)
        fits[name] = (r, s_c, s_k)
    ((si, s_c0, s_k0), (unit, s_c, s_k)) = fits.values()
    assert abs(si.num_steps - unit.num_steps) <= 1, (si.num_steps, unit.num_steps)
    back = {"C": float(unit.theta["C"]) / s_c, "hA": float(unit.theta["hA"])}
    back["kr"] = float(unit.theta["kr"]) / s_k
    first = {"C": float(si.theta["C"]) / s_c0, "hA": float(si.theta["hA"])}
    first["kr"] = float(si.theta["kr"]) / s_k0
    for name, value in back.items():
        np.testing.assert_allclose(first[name], value, rtol=1e-7)
        assert (
            abs(value - TRUTH[name])
            < 4 * float(unit.std[name]) / ({"C": s_c, "hA": 1.0, "kr": s_k}[name])
        )


def test_a_positive_start_below_positive_s_floor_names_the_bound():
    """A gain of 3e-14 in SI units (a MEMS-sized quantity) with `constraints.positive()`,
    whose bound is eps = 1e-12: the start 5e-14 is projected up to 1e-12. The warning said
    only that theta0 "lies outside the constraint set", though the start was positive; it
    now names the bound and how to lower it."""
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u)
    u = np.random.default_rng(0).standard_normal((50, 1))
    _, z = oj.simulate(model, {"a": 0.8, "b": 3e-14}, np.zeros(1), u)
    match = (
        r"theta0 lies outside the constraint set.*The start b = 5e-14 is positive but below "
        r"its lower bound 1e-12 .*`positive\(eps=\.\.\.\)`"
    )
    with pytest.warns(UserWarning, match=match):
        oj.fit(
            model,
            {"a": 0.5, "b": 5e-14},
            np.zeros(1),
            u,
            np.asarray(z),
            constraints=oj.constraints.positive(),
            estimate_x0=False,
        )
