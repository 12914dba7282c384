"""`print(result)` reads like MATLAB nlgreyest's report, and the solvers print their
settings: the stop on one line (never the RESULTS repr), the parameters in theta0's
order with their units, x0 with its standard errors, a neural residual as one row, FIT%,
RMSE and AIC; `theta_order` and `units` survive save and load."""

import re
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
from helpers import first_order_states

import oneshot_jax as oj
from oneshot_jax.internal import RESULTS_BY_NAME
from oneshot_jax.residual import MLP, count_parameters

DT = 0.05
TRUTH = {"w0sq": 4.0, "c": 0.3, "b": 1.0}


def oscillator(x, u, theta):
    """A damped oscillator with an optional residual `r` on its acceleration."""
    r = theta["r"](x)[0] if "r" in theta else 0.0
    return jnp.stack([x[1], -theta["w0sq"] * x[0] - theta["c"] * x[1] + theta["b"] * u[0] + r])


MODEL = oj.Model.from_ode(oscillator, DT, observe=lambda x, u, theta: x[:1])


def data(n_traj=None, T=120, seed=0):
    rng = np.random.default_rng(seed)
    shape = (T, 1) if n_traj is None else (n_traj, T, 1)
    u = rng.standard_normal(shape)
    x0 = np.array([1.0, 0.0]) if n_traj is None else np.tile([1.0, 0.0], (n_traj, 1))
    _, z = oj.simulate(MODEL, TRUTH, x0, u)
    return x0, u, np.asarray(z) + 0.01 * rng.standard_normal(np.shape(z))


@pytest.fixture(scope="module")
def fitted():
    """theta0 written w0sq, c, b (JAX sorts it b, c, w0sq); b fixed, x0[1] known."""
    x0, u, z = data()
    theta0 = {"w0sq": 3.0, "c": 0.2, "b": 1.0}
    return oj.fit(
        MODEL,
        theta0,
        x0,
        u,
        z,
        fixed={"w0sq": False, "c": False, "b": True},
        estimate_x0=np.array([True, False]),
        units={"w0sq": "1/s^2", "c": "1/s"},
    )


def _row(text, name):
    (line,) = [ln for ln in text.splitlines() if ln.startswith(f"  {name} ")]
    return line


def test_parameters_print_in_theta0_order_with_units(fitted):
    text = str(fitted)
    assert fitted.theta_order == ("w0sq", "c", "b")
    names = [ln.split()[0] for ln in text.splitlines() if ln.startswith("  ")]
    assert names.index("w0sq") < names.index("c") < names.index("b")
    assert "1/s^2" in _row(text, "w0sq") and "1/s" in _row(text, "c")
    assert _row(text, "b").endswith("(fixed)")
    # value, std and the 95 % interval of an estimated parameter
    v, s = float(fitted.theta["w0sq"]), float(fitted.std["w0sq"])
    assert f"{v:.6g}" in _row(text, "w0sq") and f"{s:.3g}" in _row(text, "w0sq")
    assert f"[{v - 1.96 * s:.6g}, {v + 1.96 * s:.6g}]" in _row(text, "w0sq")


def test_a_fit_started_from_a_results_theta_prints_in_the_first_fits_order(fitted):
    """result.theta is a dict in theta0's written order (JAX's own is sorted): a second
    fit from it, with LM or with Adam, prints w0sq, c, b as the first fit did."""
    assert list(fitted.theta) == ["w0sq", "c", "b"]
    x0, u, z = data()
    for solver in (oj.LevenbergMarquardt(max_steps=3), oj.Adam(max_steps=3)):
        again = oj.fit(MODEL, fitted.theta, x0, u, z, solver=solver)
        assert again.theta_order == ("w0sq", "c", "b") and list(again.theta) == ["w0sq", "c", "b"]
        names = [ln.split()[0] for ln in str(again).splitlines() if ln.startswith("  ")]
        assert names.index("w0sq") < names.index("c") < names.index("b")


def test_the_stop_is_one_readable_line_never_the_results_repr(fitted):
    text = str(fitted)
    assert "RESULTS<" not in text and "RESULTS<" not in fitted.message
    (status,) = [ln for ln in text.splitlines() if ln.startswith("status: ")]
    assert status.startswith(f"status: {fitted.status} (")
    assert "gtol" in status  # the test that fired, with its values
    lines = text.splitlines()
    assert lines[lines.index(status) + 1].startswith("loss ")
    assert " steps in " in text and "s (wall" in text
    assert "FIT% [" in text and "RMSE [" in text and "AIC " in text and "FPE " in text
    assert repr(fitted) == text
    assert fitted.success and "not a solution" not in text


def test_every_stop_prints_without_the_results_repr():
    x0, u, z = data()
    r = oj.fit(MODEL, TRUTH, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=1))
    assert r.status == "max_steps_reached"
    # A result without the values of the test (e.g. one written before they were kept):
    # the reason's own words, up to its advice.
    bare = eqx.tree_at(lambda res: res.stop_info, r, {})
    for result in (r, bare):
        (status,) = [ln for ln in str(result).splitlines() if ln.startswith("status: ")]
        assert "RESULTS<" not in str(result)
        assert status.startswith("status: max_steps_reached (") and "\n" not in status
    assert "before the first-order test held" in str(bare)
    # The intervals of a point that is not a solution say so; a solution's do not.
    assert "  (not a solution: the standard errors and intervals" in str(r)


def test_the_status_line_shows_the_whole_test_that_fired(fitted):
    """The report cuts `message` at its first semicolon: no stop's detail holds one (a
    statistical stop printed "(rank-deficient Jacobian" and lost the first-order measure)."""
    info = dict(fitted.stop_info, standard_errors=0.008, stol=0.01, first_order=1e-5)
    info.update(zero_gradient=["k"], solver_stop="converged")
    info.update(tol_loss=1.0, tol_grad=2.0, loss_at_stop=0.5, grad_norm=0.1)
    for step_test in (False, True):
        _check_status_lines(fitted, dict(info, step_test=step_test, rtol=0.01, atol=0.0))
    stat = eqx.tree_at(
        lambda r: (r.stop_reason, r.stop_info),
        fitted,
        (oj.RESULTS.statistically_converged, info),
    )
    assert "first-order measure 1e-05 (gtol" in str(stat)


def test_a_value_next_to_its_threshold_is_printed_with_the_digits_that_tell_them_apart(fitted):
    """A loss just below tol_loss (or a measure just below gtol) printed with 3 digits
    read "0.00247 < tol_loss 0.00247": the status line now adds digits until they differ."""
    info = dict(fitted.stop_info, tol_loss=0.0024742, loss_at_stop=0.00247419)
    info.update(first_order=0.0099999, gtol=0.01)
    for item in (oj.RESULTS.tol_loss, oj.RESULTS.converged):
        result = eqx.tree_at(lambda r: (r.stop_reason, r.stop_info), fitted, (item, info))
        (status,) = [ln for ln in str(result).splitlines() if ln.startswith("status: ")]
        if item == oj.RESULTS.tol_loss:
            assert "loss 0.00247419 < tol_loss 0.0024742" in status, status
        else:
            assert "first-order measure 0.0099999 <= gtol 0.01" in status, status


def _check_status_lines(fitted, info):
    for name, item in RESULTS_BY_NAME.items():
        result = eqx.tree_at(lambda r: (r.stop_reason, r.stop_info), fitted, (item, info))
        words = oj.RESULTS[result.stop_reason]
        if result.message == words:  # no values to show: the reason's words, cut
            continue
        assert result.message.endswith(f"; {words}")
        detail = result.message[: -len(words) - 2]
        assert ";" not in detail, (name, detail)
        (status,) = [ln for ln in str(result).splitlines() if ln.startswith("status: ")]
        assert status == f"status: {name} ({detail})"


def test_user_thresholds_name_their_test_and_values():
    """tol_loss / tol_grad (Algorithm 1's epsilon and delta, a success by the user's
    threshold) show the value, the threshold and, away from a stationary point, the
    first-order measure; a stop of the optional step test names rtol, not round-off."""
    x0, u, z = data()
    start = {"w0sq": 3.0, "c": 0.2, "b": 1.0}
    for solver, test in ((oj.Adam(tol_loss=10.0), "tol_loss"), (oj.Adam(tol_grad=1e3), "tol_grad")):
        r = oj.fit(MODEL, start, x0, u, z, solver=solver)
        assert r.status == test and r.success and r.num_steps == 0
        value = r.stop_info["loss_at_stop"] if test == "tol_loss" else r.stop_info["grad_norm"]
        tol = solver.tol_loss if test == "tol_loss" else solver.tol_grad
        assert r.stop_info[test] == tol and value < tol
        what = "loss" if test == "tol_loss" else "gradient norm"
        (status,) = [ln for ln in str(r).splitlines() if ln.startswith("status: ")]
        assert status.startswith(f"status: {test} ({what} {value:.3g} < {test} ")
        assert status.endswith("> gtol: not a stationary point)")
        # (its intervals are not an estimate's: the printout says so, as for a failure)
        assert f"(not a stationary point: {test} stopped the fit by your threshold" in str(r)
    r = oj.fit(MODEL, start, x0, u, z, solver=oj.LevenbergMarquardt(rtol=0.05))
    assert r.status == "stalled" and r.stop_info["step_test"] and r.stop_info["rtol"] == 0.05
    assert "the step test fired (step " in r.message and "rtol 0.05, atol 0)" in r.message
    plain = oj.fit(MODEL, start, x0, u, z)
    assert plain.status == "converged" and "step_test" not in plain.stop_info


def test_a_nan_aic_says_why():
    """The AIC of a fit whose loss is not finite says so (it blamed missing samples); a
    user's threshold met at a stationary point has no caveat."""
    x0, u, z = data()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = oj.fit(MODEL, {"w0sq": -1e6, "c": 0.2, "b": 1.0}, x0, u, z)
    assert r.status == "diverged" and not np.isfinite(r.loss)
    assert "AIC nan (the loss is not finite)" in str(r)
    assert "the loss at the start is not finite: the simulation from theta0" in r.message
    done = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, z)
    at = oj.fit(MODEL, done.theta, done.x0, u, z, solver=oj.Adam(tol_loss=1.0))
    assert at.status == "tol_loss" and "not a stationary point" not in str(at), str(at)


def test_an_optimistix_solver_stop_names_its_own_tolerances():
    """optimistix stops on its own test (changes of the step and the loss within rtol,
    atol): with a loose rtol it stops away from the solution, and the stop names that
    test and its tolerances, not "no step decreases the loss"; a stop at a solution
    names the first-order test."""
    x0, u, z = data()
    start = {"w0sq": 3.0, "c": 0.2, "b": 1.0}
    loose = oj.Optimistix(optx.LevenbergMarquardt(rtol=0.05, atol=1e-12))
    r = oj.fit(MODEL, start, x0, u, z, solver=loose)
    assert r.status == "stalled" and not r.success
    assert r.stop_info["step_test"] and r.stop_info["rtol"] == 0.05
    assert r.solver[0]["rtol"] == 0.05 and r.solver[0]["atol"] == 1e-12
    assert r.message.startswith(
        "the solver's own test on its step and loss fired (rtol 0.05, atol 1e-12): stalled, "
        "first-order measure "
    )
    assert "no step decreases the loss" not in r.message
    tight = oj.Optimistix(optx.GaussNewton(rtol=1e-10, atol=1e-14))
    ok = oj.fit(MODEL, start, x0, u, z, solver=tight)
    assert ok.status == "converged" and ok.message.startswith("first-order measure ")


def test_max_steps_of_an_optimistix_solver_and_a_validation_stop_give_their_numbers():
    """Every stop names its test with numbers: an optimistix solver at max_steps gave no
    first-order measure (it was formed only where the inner solver stopped), and a
    validation stop neither the score that chose the point nor the patience."""
    x0, u, z = data()
    start = {"w0sq": 3.0, "c": 0.2, "b": 1.0}
    # (the solver of `test_an_optimistix_solver_stop_names_its_own_tolerances`'s fit at a
    # solution, stopped short: the same compiled fit, max_steps being data)
    short = oj.Optimistix(optx.GaussNewton(rtol=1e-10, atol=1e-14), max_steps=2)
    r = oj.fit(MODEL, start, x0, u, z, solver=short)
    assert r.status == "max_steps_reached" and np.isfinite(r.stop_info["first_order"])
    assert r.message.startswith(f"first-order measure {r.stop_info['first_order']:.3g} (gtol")
    fresh = oj.fit(MODEL, r.theta, r.x0, u, z, solver=oj.Adam(max_steps=0), estimate_x0=True)
    assert r.stop_info["first_order"] == pytest.approx(fresh.stop_info["first_order"], rel=1e-6)
    x0v, uv, zv = data(seed=5)
    val = oj.Validation(uv, zv, n=10, patience=2)
    adam = oj.Adam(lr_theta=0.05, lr_x0=0.05, max_steps=400)
    v = oj.fit(MODEL, start, x0, u, z, validation=val, solver=adam)
    assert v.status == "validation"
    assert v.stop_info["validation_loss"] == v.validation_loss and v.stop_info["patience"] == 2
    assert v.message.startswith(f"lowest validation loss {v.validation_loss:.3g} (patience 2)")


def test_x0_rows_show_their_standard_errors(fitted):
    text = str(fitted)
    x0, std = fitted.x0, fitted.x0_std
    row = _row(text, "x0[0]")
    assert f"{x0[0]:.6g}" in row and f"{std[0]:.3g}" in row
    assert f"[{x0[0] - 1.96 * std[0]:.6g}," in row
    assert _row(text, "x0[1]").endswith("(fixed)")
    assert "initial state" in text


def test_several_trajectories_show_the_first_rows_and_a_count():
    # (the records of the pooled test's many-records case: the same compiled fit)
    x0, u, z = data(n_traj=8, T=60)
    r = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, z)
    text = str(r)
    assert "8 trajectories" in text
    row = _row(text, "x0[1, 0]")
    assert f"{r.x0[1, 0]:.6g}" in row and f"{r.x0_std[1, 0]:.3g}" in row
    assert "x0[4, 0]" not in text and "6 more trajectories" in text


def test_a_pooled_fit_says_so_and_gives_each_trajectory_s_fit(fitted, tmp_path):
    """Two records at different operating points printed "FIT% [99.9]" (each against the
    mean of both) where each record's own FIT% is far lower (98.3 % against 30.5 % and
    38.3 % in a probe): the line now says it is pooled, and the FIT% of each follows."""
    rng = np.random.default_rng(1)
    # Small inputs about two operating points (x settles near b u / w0sq: 0 and 1.25)
    u = 0.1 * rng.standard_normal((2, 80, 1)) + np.array([0.0, 5.0])[:, None, None]
    x0 = np.array([[0.0, 0.0], [1.25, 0.0]])
    z = np.asarray(oj.simulate(MODEL, TRUTH, x0, u)[1]) + 0.01 * rng.standard_normal((2, 80, 1))
    r = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, z)
    zhat = np.asarray(r.simulate(u)[1])
    own = [np.asarray(oj.metrics.fit_percent(z[i], zhat[i])) for i in range(2)]
    per = np.asarray(r.metrics["fit_percent_per_record"])
    assert per.shape == (2, 1)
    np.testing.assert_allclose(per, own, rtol=1e-9)
    assert float(r.metrics["fit_percent"][0]) > max(own)[0] + 1.0  # (the pooled one)
    lines = str(r).splitlines()
    fitp = f"{float(r.metrics['fit_percent'][0]):.2f}"
    assert lines[-2].startswith(f"pooled over the 2 trajectories: FIT% [{fitp}]  RMSE [")
    assert lines[-1] == f"FIT% per trajectory: [{own[0][0]:.2f}], [{own[1][0]:.2f}]"
    loaded = oj.load_result(r.save(tmp_path / "two"), model=MODEL)
    assert str(loaded) == str(r)
    # A result saved before the entry existed: the pooled line alone.
    older = eqx.tree_at(
        lambda res: res.metrics,
        r,
        {k: v for k, v in r.metrics.items() if k != "fit_percent_per_record"},
    )
    assert str(older).splitlines()[-1] == lines[-2]
    # One record: its row, and no "pooled"
    np.testing.assert_array_equal(
        fitted.metrics["fit_percent_per_record"], fitted.metrics["fit_percent"][None]
    )
    assert "pooled" not in str(fitted) and "per trajectory" not in str(fitted)
    # Many: the lowest and the highest per output
    x0, u, z = data(n_traj=8, T=60)
    r = oj.fit(MODEL, TRUTH, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=2))
    per = np.asarray(r.metrics["fit_percent_per_record"])
    assert str(r).splitlines()[-1] == (
        f"FIT% per trajectory: from [{per.min():.2f}] to [{per.max():.2f}] over the 8 "
        "trajectories (result.metrics['fit_percent_per_record'])"
    )


def test_a_neural_residual_is_one_row():
    x0, u, z = data(T=60)
    net = MLP(2, 1, (8,), key=jax.random.PRNGKey(0))
    theta0 = {"w0sq": 3.0, "c": 0.2, "b": 1.0, "r": net}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # weights are never all identifiable
        r = oj.fit(
            MODEL,
            theta0,
            x0,
            u,
            z,
            solver=oj.LevenbergMarquardt(max_steps=3),
            units={"r": "m/s^2"},
        )
    text = str(r)
    n = count_parameters(net)
    assert f"MLP, {n} weights" in _row(text, "r") and "m/s^2" in _row(text, "r")
    # (the rows; the fit's warning listed after them names the weights in J's null space)
    rows = "\n".join(ln for ln in text.splitlines() if not ln.startswith("warning:"))
    assert "layers" not in rows and "weight[" not in rows
    names = [ln.split()[0] for ln in text.splitlines() if ln.startswith("  ")]
    assert names.index("w0sq") < names.index("c") < names.index("b") < names.index("r")
    fixed = oj.fit(
        MODEL,
        theta0,
        x0,
        u,
        z,
        solver=oj.LevenbergMarquardt(max_steps=3),
        fixed={"w0sq": False, "c": False, "b": False, "r": True},
    )
    assert _row(str(fixed), "r").endswith(f"MLP, {n} weights (fixed)")


def test_integer_data_of_theta_print_as_data_rows():
    """An integer scalar of NumPy is data (an exponent here), not a parameter: it prints
    with its value as "(data, not estimated)"; a module's own static fields do not."""

    def powered(x, u, theta):
        r = theta["r"](x)[0]
        acc = -theta["w0sq"] * x[0] ** theta["p"] - theta["c"] * x[1] + theta["b"] * u[0]
        return jnp.stack([x[1], acc + r])

    model = oj.Model.from_ode(powered, DT, observe=lambda x, u, theta: x[:1])
    x0, u, z = data(T=60)
    net = MLP(2, 1, (4,), key=jax.random.PRNGKey(0))
    theta0 = {"w0sq": 3.0, "p": np.int64(1), "c": 0.2, "b": 1.0, "r": net}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the integer leaf's warning; the weights
        r = oj.fit(
            model, theta0, x0, u, z, solver=oj.LevenbergMarquardt(max_steps=2), units={"p": "-"}
        )
    text = str(r)
    assert _row(text, "p").split() == ["p", "-", "1", "(data,", "not", "estimated)"]
    assert text.count("(data, not estimated)") == 1
    n = 3 + count_parameters(net)
    assert f"{n} of {n} parameters" in text  # p is not one


def test_a_windowed_fit_says_its_fit_is_over_the_windows(fitted):
    """Multiple shooting restarts each window from its own x0: its FIT% is not the model's
    simulation of the record (93 % against -40 % in an audit), and the printout says so."""
    x0, u, z = data(T=120)
    # (6 windows: more than the printout lists, so one fit shows the count of the rest)
    r = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, z, window=20)
    text = str(r)
    assert "(over the 6 windows, each from its own fitted x0: not a simulation" in text
    assert "pooled over the 6 windows: FIT% [" in text and "\nFIT% per window: [" in text
    assert np.shape(r.residuals) == (6, 20, 1)
    assert "over the" not in str(fitted)
    # Its initial states are the windows', not trajectories.
    assert "(per window, 6 windows)" in text and "trajector" not in text
    assert "... and 4 more windows (result.x0" in text
    # Each window's rows say the sample it starts at (window 1: sample 20).
    assert f"  x0[1, 0] (sample {int(r.window_starts[1])})" in text
    assert int(r.window_starts[1]) == 20


def test_units_are_checked():
    x0, u, z = data(T=20)
    theta0 = {"w0sq": 3.0, "c": 0.2, "b": 1.0}
    with pytest.raises(ValueError, match=r"`units` names 'k'.*valid names: w0sq, c, b\."):
        oj.fit(MODEL, theta0, x0, u, z, units={"k": "N/m"})
    with pytest.raises(ValueError, match=r"`units\['c'\]` must be a string"):
        oj.fit(MODEL, theta0, x0, u, z, units={"c": 1.0})
    with pytest.raises(TypeError, match="`units`"):
        oj.fit(MODEL, theta0, x0, u, z, units=["1/s"])


def test_named_states_and_outputs_label_the_printouts_and_the_plot(fitted, tmp_path):
    """`Model(states=..., outputs=...)` (MATLAB's InitialStates.Name and OutputName) name
    the initial-state rows, the FIT and RMSE per output, an x0 estimate's rows and
    `plot.compare`'s axis; the numbers are those of the same fit without names, and a
    result loaded without the model prints indices again."""
    named = oj.Model.from_ode(
        oscillator,
        DT,
        observe=lambda x, u, theta: x[:1],
        states=["q (m)", "v (m/s)"],
        outputs="q (m)",
    )
    assert named.states == ("q (m)", "v (m/s)") and named.outputs == ("q (m)",)
    x0, u, z = data()
    kw = dict(fixed={"b": True}, estimate_x0=np.array([True, False]))
    r = oj.fit(named, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, z, **kw)
    plain = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, z, **kw)
    text, before = str(r), str(plain)
    assert _row(text, "x0[q (m)]").split()[-4:] == _row(before, "x0[0]").split()[-4:]
    assert _row(text, "x0[v (m/s)]").endswith("(fixed)")
    fit, rmse = r.metrics["fit_percent"][0], r.metrics["rmse"][0]
    assert f"FIT% [q (m): {fit:.2f}]  RMSE [q (m): {rmse:.4g}]" in text
    assert f"FIT% [{fit:.2f}]  RMSE [{rmse:.4g}]" in before
    est = r.predict(u, z[:20]).estimate
    rows = str(est).splitlines()[1:]
    assert rows[0].startswith("  x0[q (m)]  ") and rows[1].startswith("  x0[v (m/s)]")
    assert rows[0].index(" std ") == rows[1].index(" std ")  # (the columns line up)
    assert oj.plot.compare(z, r, u=u).axes[0].get_ylabel() == "q (m)"
    assert oj.plot.compare(z, plain, u=u).axes[0].get_ylabel() == "output"
    path = r.save(tmp_path / "named")
    assert "x0[0]" in str(oj.load_result(path))
    # The names are labels, not what the model computes: the result loads with the same
    # dynamics named or not (with the names in the file's model record, neither loaded)
    assert "x0[q (m)]" in str(oj.load_result(path, model=named))
    assert "x0[0]" in str(oj.load_result(path, model=MODEL))
    assert "x0[0]" in str(oj.load_result(plain.save(tmp_path / "plain"), model=MODEL))
    assert "x0[q (m)]" in str(oj.load_result(tmp_path / "plain.npz", model=named))
    # Several records: the record's index and the name
    xs, us, zs = data(n_traj=2, T=40)
    both = oj.fit(named, TRUTH, xs, us, zs)
    per = both.metrics["fit_percent_per_record"][:, 0]
    assert "  x0[1, v (m/s)]" in str(both)
    assert f"FIT% per trajectory: [q (m): {per[0]:.2f}], [q (m): {per[1]:.2f}]" in str(both)
    # Names of another count than the data's entries, or not strings, are refused
    for field, names, count in (("states", ["q"], "n_x = 2"), ("outputs", ["q", "v"], "n_z = 1")):
        wrong = oj.Model.from_ode(
            oscillator, DT, observe=lambda x, u, theta: x[:1], **{field: names}
        )
        with pytest.raises(ValueError, match=rf"the model's `{field}` holds .* {count}: give one"):
            oj.fit(wrong, TRUTH, x0, u[:20], z[:20])
    with pytest.raises(TypeError, match=r"`states` must be a string or a list of strings"):
        oj.Model(oscillator, states=[0, 1])


def test_warnings_name_the_initial_states_the_model_names():
    """The rank-deficiency warning of `fit` and the observability warning of
    `estimate_x0` name an initial state as the printouts do, where the model names it; a
    state the output never sees is the one named."""

    def step(x, u, theta):
        return jnp.stack([theta["a"] * x[0] + u[0], x[1]])

    def observe(x, u, theta):
        return x[:1]

    named = oj.Model(step, observe=observe, states=["q", "idle"], outputs="q")
    u = np.random.default_rng(0).normal(size=(50, 1))
    _, z = oj.simulate(named, {"a": 0.5}, np.array([1.0, 2.0]), u)
    for model, label in ((named, "x0[idle]"), (oj.Model(step, observe=observe), "x0[1]")):
        with pytest.warns(UserWarning, match=rf"initial states \['{re.escape(label)}'\]"):
            oj.fit(model, {"a": 0.3}, np.array([0.5, 1.0]), u, z)
        with pytest.warns(UserWarning, match=rf"entries \['{re.escape(label)}'\] are not"):
            oj.estimate_x0(model, {"a": 0.5}, u, z, n=10, x0=np.zeros(2))
    # Several records: the record's index and the name
    with pytest.warns(UserWarning, match=r"'x0\[0, idle\]', 'x0\[1, idle\]'"):
        oj.fit(
            named,
            {"a": 0.3},
            np.array([[0.5, 1.0], [0.2, 1.0]]),
            np.stack([u, u]),
            np.stack([z, z]),
        )


def test_theta_order_and_units_round_trip_through_save_and_load(fitted, tmp_path):
    loaded = oj.load_result(fitted.save(tmp_path / "osc"), model=MODEL)
    assert loaded.theta_order == fitted.theta_order == ("w0sq", "c", "b")
    # (theta and std as written, not in JAX's sorted order)
    assert list(loaded.theta) == list(fitted.theta) == ["w0sq", "c", "b"]
    assert list(loaded.std) == list(fitted.std) == ["w0sq", "c", "b"]
    assert loaded.units == fitted.units == {"w0sq": "1/s^2", "c": "1/s"}
    assert eqx.tree_equal(loaded, fitted) is True
    assert str(loaded) == str(fitted)


def test_intervals_are_arrays_as_the_standard_errors_are(fitted, tmp_path):
    # (`ci95` entries were np.float64 where `std` and `theta` hold 0-d arrays)
    loaded = oj.load_result(fitted.save(tmp_path / "osc"), model=MODEL)
    for r in (fitted, loaded):
        lo, hi = r.ci95
        for name in ("w0sq", "c", "b"):
            for a in (lo[name], hi[name], r.std[name]):
                assert type(a) is np.ndarray and a.shape == np.shape(r.theta[name]) == ()
        assert float(lo["c"]) == float(r.theta["c"]) - 1.96 * float(r.std["c"])


def test_nested_dicts_keep_their_written_order():
    from oneshot_jax.internal import theta_order

    theta = {
        "z": {"q": 1.0, "a": 2.0},
        "b": [3.0, 4.0],
        "m": MLP(2, 1, (4,), key=jax.random.PRNGKey(0)),
    }
    assert theta_order(theta) == ("z.q", "z.a", "b.0", "b.1", "m")


class _AttrDict(dict):
    """A dict with attribute access (as easydict or ml_collections give), a pytree node of
    its own type."""

    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None


jax.tree_util.register_pytree_with_keys(
    _AttrDict,
    lambda d: ([(jax.tree_util.DictKey(k), d[k]) for k in sorted(d)], tuple(sorted(d))),
    lambda keys, values: _AttrDict(zip(keys, values)),
)


def test_a_dict_subclass_theta_comes_back_in_its_own_type():
    """A theta0 of a dict subclass (attribute access) or an OrderedDict: `result.theta`
    was rebuilt as a plain dict in theta0's written order, on which a model reading
    `theta.w0sq` failed in `result.simulate` and a refit, and whose structure differed
    from theta0's. Each now comes back in its own type."""
    x0, u, z = data()

    def attribute(x, u, th):
        return oscillator(x, u, {"w0sq": th.w0sq, "c": th.c, "b": th.b})

    model = oj.Model.from_ode(attribute, DT, observe=lambda x, u, theta: x[:1])
    r = oj.fit(model, _AttrDict(w0sq=3.0, c=0.2, b=1.0), x0, u, z)
    assert type(r.theta) is _AttrDict and type(r.std) is _AttrDict
    np.testing.assert_allclose(np.asarray(r.simulate(u)[1]), r.residuals + z, atol=1e-12)
    again = oj.fit(model, r.theta, r.x0, u, z)
    assert type(again.theta) is _AttrDict
    import collections

    theta0 = collections.OrderedDict(w0sq=3.0, c=0.2, b=1.0)
    r = oj.fit(MODEL, theta0, x0, u, z)
    assert type(r.theta) is collections.OrderedDict and list(r.theta) == ["w0sq", "c", "b"]
    assert jax.tree_util.tree_structure(r.theta) == jax.tree_util.tree_structure(theta0)


def test_solver_reprs_show_every_setting():
    lm = oj.LevenbergMarquardt()
    assert repr(lm) == (
        "LevenbergMarquardt(rtol=0.0, atol=0.0, gtol=1e-08, stol=0.01, max_steps=100, "
        "mu0=0.001, strategy='auto', linear_solver='auto', cg_rtol=1e-08, cg_max_steps=50)"
    )
    assert repr(oj.Adam()).startswith("Adam(lr_theta=0.001, lr_x0=0.0001, b1=0.9, b2=0.999,")
    namespace = {name: getattr(oj, name) for name in ("LevenbergMarquardt", "GaussNewton")}
    namespace.update(Adam=oj.Adam, LBFGS=oj.LBFGS)
    for solver in (
        oj.LevenbergMarquardt(gtol=1e-6, max_steps=7),
        oj.GaussNewton(linear_solver="cg"),
        oj.Adam(lr_theta=1e-2),
        oj.LBFGS(memory_size=5),
    ):
        text = repr(solver)
        fields = [f.name for f in solver.__dataclass_fields__.values()]
        assert all(f"{name}=" in text for name in fields), text
        assert eval(text, namespace) == solver  # every option, with its value
    wrapped = repr(oj.Optax(optax.adam(1e-2), max_steps=10))
    assert wrapped.startswith("Optax(transform=<optax.") and "max_steps=10, " in wrapped
    assert "\n" not in wrapped
    optimistix = repr(oj.Optimistix(optx.LevenbergMarquardt(rtol=1e-12, atol=1e-20)))
    assert optimistix == (
        "Optimistix(solver=optx.LevenbergMarquardt(rtol=1e-12, atol=1e-20), max_steps=256, "
        "gtol=1e-08, strategy='auto')"
    )
    schedule = repr(oj.Adam(lr_theta=optax.cosine_decay_schedule(1e-2, 10)))
    assert "lr_theta=<function cosine_decay_schedule>" in schedule


def test_intervals_of_x0_print_when_every_parameter_is_fixed():
    """With theta wholly fixed the covariance of theta is empty, but x0's is computed:
    its intervals print (an empty covariance means "not computed" only with free
    entries of theta)."""
    x0, u, z = data()
    res = oj.fit(MODEL, TRUTH, x0 * 0.9, u, z, fixed=True)
    assert np.shape(res.covariance) == (0, 0) and np.all(np.isfinite(res.x0_std))
    text = str(res)
    assert "(not computed)" not in text
    lo, hi = res.x0[0] - 1.96 * res.x0_std[0], res.x0[0] + 1.96 * res.x0_std[0]
    assert f"[{lo:.6g}, {hi:.6g}]" in _row(text, "x0[0]")


def test_simulate_takes_the_ragged_records_the_result_was_fitted_on():
    rng = np.random.default_rng(0)
    us = [rng.standard_normal((T, 1)) for T in (100, 80, 60)]
    x0 = np.tile([1.0, 0.0], (3, 1))
    _, zs = oj.simulate(MODEL, TRUTH, x0, us)
    res = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, us, zs)
    _, again = res.simulate(us)
    _, direct = oj.simulate(MODEL, res.theta, res.x0, us)
    assert [np.shape(a) for a in again] == [(100, 1), (80, 1), (60, 1)]
    for a, b in zip(again, direct):
        np.testing.assert_array_equal(a, b)


def _first_order_ar(T):
    """x[k+1] = a x + b u, z = x, T noisy samples: 3 unknowns (a, b, x0)."""
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u)
    u = np.array([[1.0], [-0.5], [0.3], [0.8], [-0.2]])[:T]
    z = np.asarray(oj.simulate(model, {"a": 0.8, "b": 0.5}, np.array([1.0]), u)[1])
    return model, u, z + np.array([[0.01], [-0.02], [0.015], [0.005], [-0.01]])[:T]


@pytest.mark.parametrize("T", [2, 3])
def test_no_more_data_than_estimates_is_not_called_unidentifiable(T, tmp_path):
    """With no more measured outputs than estimated entries, sigma^2 = SSE / dof is unknown
    and every std is inf, identifiable or not: the fit warns and names that (T = 3: J has
    full rank 3, so "not identifiable" was false; it was printed for every entry, x0
    included). One more sample (T = 4, below) gives finite standard errors. (T = 1, which
    x0 alone fits, is refused: `test_windows_subset.py`.)"""
    model, u, z = _first_order_ar(T)
    with pytest.warns(UserWarning, match=rf"no more measured output values \({T}\) than "):
        r = oj.fit(model, {"a": 0.5, "b": 0.2}, np.array([0.5]), u, z)
    assert np.isinf(r.std["a"]) and np.isinf(r.std["b"]) and np.isinf(r.x0_std).all()
    assert r.diagnostics["degrees_of_freedom"] == T - 3
    for text in (str(r), str(oj.load_result(r.save(tmp_path / "r")))):
        # (the rows; at T = 2 the fit's warning of a rank-deficient J, listed after them,
        # is right: 2 samples leave 3 estimates a null direction)
        rows = "\n".join(s for s in text.splitlines() if not s.startswith("warning:"))
        assert "not identifiable" not in rows
        assert text.count("(unknown: no more data than estimates)") == 3


def test_one_degree_of_freedom_gives_finite_standard_errors():
    model, u, z = _first_order_ar(4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = oj.fit(model, {"a": 0.5, "b": 0.2}, np.array([0.5]), u, z)
    assert np.isfinite(r.std["a"]) and np.isfinite(r.x0_std).all()
    assert "degrees_of_freedom" not in r.diagnostics
    assert "no more data than estimates" not in str(r)


def test_a_stop_without_a_covariance_does_not_speak_of_its_standard_errors():
    """`covariance=None` and a stop that is not a solution: every row says "(not
    computed)", and the note under the status said "the standard errors and intervals
    below are those of the linearisation"."""
    x0, u, z = data()
    theta0 = {"w0sq": 3.0, "c": 0.2, "b": 1.0}
    solver = oj.LevenbergMarquardt(max_steps=1)
    for covariance, says in (("classical", True), (None, False)):
        r = oj.fit(MODEL, theta0, x0, u, z, solver=solver, covariance=covariance)
        assert not r.success
        assert ("standard errors and intervals below" in str(r)) is says
        assert ("(not computed)" in str(r)) is not says


def test_an_interval_far_narrower_than_its_value_prints_apart():
    """Noise 1e-6: a standard error 1e-6 of the value printed `2  1.42e-06  [2, 2]` at six
    digits; the value and the interval take the digits that show it."""
    x0, u, z = data()
    _, clean = oj.simulate(MODEL, TRUTH, x0, u)
    noisy = np.asarray(clean) + 1e-6 * np.random.default_rng(1).standard_normal(np.shape(z))
    r = oj.fit(MODEL, {"w0sq": 3.0, "c": 0.2, "b": 1.0}, x0, u, noisy)
    row = next(line for line in str(r).splitlines() if line.lstrip().startswith("w0sq"))
    lo, hi = row.split("[")[1].rstrip("]").split(", ")
    assert float(lo) < float(hi), row
    assert float(lo) < float(r.theta["w0sq"]) < float(hi)


def test_the_output_weight_is_printed():
    """MATLAB's nlgreyest report names its OutputWeight; the printout said only that a
    weight had been estimated (`weight="noise"`), not which, and nothing of one given."""
    model = oj.Model(lambda x, u, th: jnp.stack([th["a"] * x[0] + u[0], 0.5 * x[0] + 0.3 * x[1]]))
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    _, z = oj.simulate(model, {"a": 0.8}, np.array([1.0, 0.0]), u)
    z = np.asarray(z) + np.array([0.01, 0.3]) * rng.standard_normal((200, 2))
    x0 = np.array([1.0, 0.0])
    given = oj.fit(model, {"a": 0.5}, x0, u, z, weight=np.array([1.0, 4.0]))
    assert "  (output weight Q diagonal [1, 4], as given)" in str(given)
    full = oj.fit(model, {"a": 0.5}, x0, u, z, weight=np.array([[2.0, 0.5], [0.5, 1.0]]))
    assert "Q diagonal [2, 1] and off-diagonal terms (`result.weight`), as given" in str(full)
    noise = oj.fit(model, {"a": 0.5}, x0, u, z, weight="noise")
    q = np.diag(noise.weight) if np.ndim(noise.weight) == 2 else noise.weight
    assert f"; Q diagonal [{q[0]:.4g}, {q[1]:.4g}]" in str(noise)
    assert "output weight" not in str(oj.fit(model, {"a": 0.5}, x0, u, z))


def test_float32_standard_errors_lost_to_round_off_say_so():
    """x+ = a x + b u, z = x + c with the input 10 + 0.03 N(0, 1): the gain, the offset
    and x0 nearly collinear. In float32, J^T J's round-off makes them read null (std inf)
    while float64 determines all of them: the printout said "(not identifiable)" and the
    warning "not identifiable from these data"; they now say "not resolved in float32"
    and name float64 as the remedy."""
    rng = np.random.default_rng(0)
    T = 300
    u = 10 + 0.03 * rng.standard_normal((T, 1))
    x = first_order_states(u, x0=2.0)
    z = (x + 3.0 + 0.01 * rng.standard_normal(T))[:, None]
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u, lambda x, u, th: x + th["c"])
    f = np.float32
    theta0 = {"a": f(0.9), "b": f(0.5), "c": f(3.0)}
    x0 = np.array([z[0, 0] - 3.0], f)
    with pytest.warns(UserWarning, match="singular to float32 precision") as caught:
        r = oj.fit(model, theta0, x0, u.astype(f), z.astype(f))
    assert not np.isfinite(r.std["b"])
    assert "(not resolved in float32)" in str(r) and "(not identifiable)" not in str(r)
    assert not any("not identifiable from these data" in str(w.message) for w in caught)
    r64 = oj.fit(model, {k: float(v) for k, v in theta0.items()}, x0.astype(float), u, z)
    assert all(np.isfinite(r64.std[k]) for k in "abc")


def _lag(x, u, theta):
    # x' = (K u - x) / tau: at tau = 0.02 s and dt = 0.05 s, |lambda| h = 2.5 for RK4
    return (theta["K"] * u - x) / theta["tau"]


def test_a_fits_warnings_are_kept_and_printed_whatever_the_filters_show(tmp_path):
    """What `fit` warns of about a fit (here a mode beyond RK4's accurate range) is in
    `result.warnings` and in its printout also where the filters hide it, survives save
    and load, and is still shown where they do not; a fit with nothing to warn of has
    none."""
    model = oj.Model.from_ode(_lag, 0.05)
    rng = np.random.default_rng(0)
    u = np.sin(0.1 * np.arange(200))[:, None]
    truth = {"tau": 0.02, "K": 2.0}
    _, z = oj.simulate(model, truth, np.zeros(1), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = oj.fit(model, {"tau": 0.021, "K": 2.0}, np.zeros(1), u, z)
    assert r.success
    (message,) = r.warnings
    assert "stability limit" in message and "substeps=2" in message
    assert f"warning: {message}" in str(r).splitlines()
    path = r.save(tmp_path / "r.npz")
    assert oj.load_result(path, model=model).warnings == r.warnings
    with pytest.warns(RuntimeWarning, match="stability limit"):
        shown = oj.fit(model, {"tau": 0.021, "K": 2.0}, np.zeros(1), u, z)
    assert shown.warnings == r.warnings
    slow = {"tau": 0.5, "K": 2.0}  # (|lambda| h = 0.1: nothing to warn of)
    _, z = oj.simulate(model, slow, np.zeros(1), u)
    z = np.asarray(z) + 0.01 * rng.standard_normal(z.shape)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = oj.fit(model, {"tau": 0.4, "K": 1.5}, np.zeros(1), u, z)
    assert quiet.success and quiet.warnings == () and "warning:" not in str(quiet)


def test_residuals_that_are_not_white_are_said_so():
    """A fit of the right model to data with coloured noise (an AR(1) of coefficient 0.9)
    converges, but its residuals are not white: the printout says so with resid's
    numbers (`metrics.residual_correlations`) and that the classical standard errors
    assume white residuals; with white noise, no line; with Newey-West standard errors,
    no remark on them."""
    # (T = 120, the length of `data()`: the fits of the white and the coloured record are
    # the compiled fit of the module's other plain fits)
    T = 120
    rng = np.random.default_rng(3)
    u = rng.standard_normal((T, 1))
    x0 = np.array([1.0, 0.0])
    _, z = oj.simulate(MODEL, TRUTH, x0, u)
    theta0 = {"w0sq": 3.5, "c": 0.4, "b": 0.8}
    white = oj.fit(MODEL, theta0, x0, u, np.asarray(z) + 0.02 * rng.standard_normal((T, 1)))
    assert white.success and "residuals not white" not in str(white)
    noise = np.zeros(T)
    for k in range(1, T):
        noise[k] = 0.9 * noise[k - 1] + 0.02 * rng.standard_normal()
    coloured = np.asarray(z) + noise[:, None]
    r = oj.fit(MODEL, theta0, x0, u, coloured)
    rc = oj.metrics.residual_correlations(r.residuals, None, 25)
    assert r.success and not rc.white[0]
    (line,) = [s for s in str(r).splitlines() if "residuals not white" in s]
    assert f"r_e(1) = {rc.auto[26, 0]:.3g}" in line
    assert f"{100 * rc.auto_outside[0]:.0f} % of the lags outside +-{rc.bound[0]:.3g}" in line
    assert "the standard errors assume white residuals" in line
    assert ": a model error, coloured noise or a bad minimum" in line  # (no weight named)
    robust = oj.fit(MODEL, theta0, x0, u, coloured, covariance=oj.NeweyWest())
    (line,) = [s for s in str(robust).splitlines() if "residuals not white" in s]
    assert "assume white" not in line
    # A diverged fit's returned point is not a fit's: no line (it advised on standard
    # errors the printout does not have)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lost = oj.fit(MODEL, theta0, x0, u, coloured, solver=oj.Adam(lr_theta=1e3, max_steps=50))
    assert lost.status == "diverged" and np.isfinite(float(lost.loss))
    assert "residuals not white" not in str(lost)


def test_an_array_parameter_of_many_entries_prints_as_one_line():
    """A 12 x 12 matrix A (144 entries) printed 144 rows (a 256 x 256 one 65536, 3.4 MB
    of "inf (not computed)"); an array of more than 100 entries is one line with its shape
    and range, as a module is, and a smaller one keeps its rows."""
    n = 12
    model = oj.Model(lambda x, u, th: th["A"] @ x + u[0] * th["b"], lambda x, u, th: x[:1])
    rng = np.random.default_rng(0)
    A = 0.5 * np.eye(n) + 0.01 * rng.standard_normal((n, n))
    u = rng.standard_normal((50, 1))
    _, z = oj.simulate(model, {"A": A, "b": np.ones(n)}, np.zeros(n), u)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = oj.fit(
            model,
            {"A": 0.9 * A, "b": np.ones(n)},
            np.zeros(n),
            u,
            np.asarray(z),
            solver=oj.LBFGS(max_steps=1),
            covariance=None,
            estimate_x0=False,
        )
    lines = str(r).splitlines()
    (row,) = [line for line in lines if line.lstrip().startswith("A ")]
    flat = np.asarray(r.theta["A"]).ravel()
    assert f"array of shape (12, 12), 144 numbers in [{flat.min():.4g}, {flat.max():.4g}]" in row
    assert not any(line.lstrip().startswith("A[") for line in lines)
    assert sum(line.lstrip().startswith("b[") for line in lines) == n
