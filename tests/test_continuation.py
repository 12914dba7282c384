"""Bad minima of the simulation error (issue 21): horizon continuation reaches the truth
where a whole-record fit converges to a bad minimum; the bad-basin check warns there and
not at the truth; the stability check warns when a `Model.from_ode` model runs beyond its
integrator's stability limit, and not inside it."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

DT, T = 0.05, 400
TRUTH = {"w0sq": 9.0, "b": 0.3}
START = {"w0sq": 4.0, "b": 0.1}  # far: the whole-record fit converges to a bad minimum


def pendulum(x, u, p):
    return jnp.stack([x[1], -p["w0sq"] * jnp.sin(x[0]) - p["b"] * x[1] + u[0]])


MODEL = oj.Model.from_ode(pendulum, DT, observe=lambda x, u, p: x[:1])


def _data():
    """A pendulum driven by three sines (one of them near its resonance, 3 rad/s), its
    angle measured with noise 0.01 rad."""
    rng = np.random.default_rng(0)
    t = DT * np.arange(T)
    u = sum(np.sin(f * t + rng.uniform(0, 6)) for f in (1.5, 3.0, 6.0))[:, None]
    _, z = oj.simulate(MODEL, TRUTH, np.zeros(2), u)
    return u, np.asarray(z) + 0.01 * rng.standard_normal((T, 1))


U, Z = _data()


def _no_warnings(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kwargs)


@pytest.fixture(scope="module")
def plain():
    """The whole-record fit from START; it warns of its FIT below 0 (a success worse
    than the outputs' mean: the truth and the least-squares optimum are above 0)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = oj.fit(MODEL, START, np.zeros(2), U, Z)
    assert [str(w.message)[:60] for w in caught] == [
        "the fit reports converged, but its simulation fits an output"
    ]
    assert "FIT -" in str(caught[0].message) and "oj.check_basin" in str(caught[0].message)
    return result


def test_an_output_below_its_noise_is_no_sign_of_a_bad_minimum():
    """A correct model with a second sensor that barely sees the state (0.005 x under a
    noise of 0.05): at the optimum, as at the truth, its FIT is a little below 0 on some
    records (-0.39 % here), and `fit` warned of a bad minimum on 30 % of such records.
    The warning waits for a FIT below -450 / n % (-2.25 % over these 200 samples)."""
    model = oj.Model(
        lambda x, u, p: p["a"] * x + p["b"] * u,
        lambda x, u, p: jnp.concatenate([x, 0.005 * x]),
    )
    rng = np.random.default_rng(3004)
    u = rng.standard_normal((200, 1))
    z = np.asarray(oj.simulate(model, {"a": 0.9, "b": 0.5}, np.array([1.0]), u)[1])
    z = z + 0.05 * rng.standard_normal((200, 2))
    r = _no_warnings(oj.fit, model, {"a": 0.85, "b": 0.45}, z[0, :1], u, z)
    assert r.success and -2.25 < float(r.metrics["fit_percent"][1]) < 0


@pytest.fixture(scope="module")
def continued():
    return _no_warnings(oj.fit_continuation, MODEL, START, np.zeros(2), U, Z, windows=(50,))


def _rel(theta):
    return {k: abs(float(theta[k]) / v - 1) for k, v in TRUTH.items()}


def test_the_whole_record_fit_converges_to_a_bad_minimum(plain):
    """The case is hard: the plain fit 'converges' far from the truth with a FIT below
    zero (without this, the tests below could not fail)."""
    assert plain.success
    assert plain.metrics["fit_percent"][0] < 0
    assert _rel(plain.theta)["w0sq"] > 0.3


def test_continuation_reaches_the_truth(continued, plain):
    cont = continued
    assert cont.success and cont.result.success
    assert [s.window for s in cont.stages] == [50, None]
    assert all(e < 0.01 for e in _rel(cont.result.theta).values()), cont.result.theta
    # at the noise level (0.01 rad), where the plain fit is far from it
    assert abs(float(cont.result.metrics["rmse"][0]) - 0.01) < 0.001
    assert float(cont.result.loss) < 1e-3 * float(plain.loss)
    last = cont.stages[-1]
    assert last.loss == float(cont.result.loss) and last.status == cont.result.status
    assert last.num_steps == cont.result.num_steps
    assert "Horizon continuation, 2 stages" in str(cont)


def test_each_stage_keeps_its_theta(continued):
    """Stage 1's theta is the windowed fit from the start (a fit of its own, not the
    last stage's theta), the last stage's the result's."""
    first, last = continued.stages
    windowed = _no_warnings(oj.fit, MODEL, START, np.zeros(2), U, Z, window=50)
    for k in TRUTH:
        assert float(first.theta[k]) == pytest.approx(float(windowed.theta[k]), rel=1e-12)
        assert float(last.theta[k]) == float(continued.result.theta[k])
    assert float(first.theta["w0sq"]) != float(last.theta["w0sq"])


def test_the_basin_check_warns_on_the_bad_minimum_only(plain, continued):
    with pytest.warns(RuntimeWarning, match="bad minimum.*fit_continuation"):
        bad = oj.check_basin(plain, U, Z, window=50)
    assert bad.bad_basin and bad.window_fit_percent[0] > 90
    # the windowed fit found the basin: its theta is a start for the whole record
    assert all(e < 0.01 for e in _rel(bad.windowed.theta).values())
    good = _no_warnings(oj.check_basin, continued.result, U, Z, window=50)
    assert not good.bad_basin
    assert abs(good.window_fit_percent[0] - good.fit_percent[0]) < 1
    # Each prints one line with both FITs and its verdict (it dumped the windowed fit)
    fits = [f"{a[0]:.3g} %" for a in (bad.fit_percent, bad.window_fit_percent)]
    assert str(bad) == repr(bad) and len(str(bad).splitlines()) == 1
    assert f"FIT {fits[0]} on the whole record, {fits[1]} in the windows" in str(bad)
    assert str(bad).endswith("multistart over the physical parameters.")
    assert str(good).endswith("(their fit: converged): no sign of a bad basin.")


def test_continuation_of_a_time_stamped_record():
    """With `t=`, every stage's windows start from states simulated at their own sample
    times (stage 2 raised "pass the sample times as t=" before)."""
    timed = oj.Model.from_ode(pendulum, observe=lambda x, u, p: x[:1], max_step=0.05, substeps=4)
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.choice([0.03, 0.05, 0.08], size=T))
    u = (np.sin(1.3 * t) + np.sin(3.4 * t + 1))[:, None]
    _, z = oj.simulate(timed, TRUTH, np.zeros(2), u, t=t)
    z = np.asarray(z) + 0.01 * rng.standard_normal((T, 1))
    c = oj.fit_continuation(timed, START, np.zeros(2), u, z, windows=(50, 100), t=t)
    assert [s.window for s in c.stages] == [50, 100, None]
    assert c.result.success and max(_rel(c.result.theta).values()) < 0.01


def test_doubling_schedule():
    """start and factor give the windows (50, 150, then the whole record); each stage
    starts from the last one's theta and states. Windows of 150 leave a tail of 100
    samples that fills no window: the whole record's stage fits it, so the continuation
    does not warn of it (`_no_warnings` turns a warning into an error)."""
    cont = _no_warnings(oj.fit_continuation, MODEL, START, np.zeros(2), U, Z, start=50, factor=3)
    assert [s.window for s in cont.stages] == [50, 150, None]
    assert cont.success
    assert all(e < 0.01 for e in _rel(cont.result.theta).values())


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"windows": (100, 50)}, "increase"),
        ({"windows": (50, 400)}, "shorter than the record"),
        ({"windows": ()}, "non-empty"),
        ({"windows": (2.5,)}, "positive integers"),
        ({"start": 400}, "shorter than the record"),
        ({"start": 0}, "positive integer"),
        ({"factor": 1}, "factor"),
        # (start and factor were ignored beside windows; a dict's keys were the lengths)
        ({"windows": (40,), "start": 10}, "pass `windows` or them, not both"),
        ({"windows": (40,), "factor": 3}, "pass `windows` or them, not both"),
        ({"windows": {40: 1}}, "a sequence of window lengths .* got dict"),
        ({"window": 50}, "window"),
        ({"multistart": True}, "multistart"),
        # It said "`window` cannot be combined with `aggregate`", a `window` never passed.
        (
            {"aggregate": oj.Aggregate(0, [(0, 30)], [0.1])},
            "`aggregate` is not a keyword of `fit_continuation`",
        ),
    ],
)
def test_continuation_rejects_bad_arguments(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        oj.fit_continuation(MODEL, START, np.zeros(2), U, Z, **kwargs)


def test_continuation_takes_one_record():
    with pytest.raises(ValueError, match="one record"):
        oj.fit_continuation(MODEL, START, np.zeros((2, 2)), U[None], Z[None])
    # A transposed u was blamed on the windows ("shorter than the record (T = 1)").
    with pytest.raises(ValueError, match=r"same number of samples .*is `u` transposed"):
        oj.fit_continuation(MODEL, START, np.zeros(2), U.T, Z, windows=[50])


def test_basin_check_rejects_bad_arguments(plain):
    with pytest.raises(TypeError, match="FitResult"):
        oj.check_basin(START, U, Z)
    with pytest.raises(ValueError, match="window"):
        oj.check_basin(plain, U, Z, window=T)
    with pytest.raises(ValueError, match=r"is it transposed\? u is \(T, n_u\)"):
        oj.check_basin(plain, U.T, Z)
    with pytest.raises(ValueError, match="margin"):
        oj.check_basin(plain, U, Z, margin=-1.0)
    with pytest.raises(TypeError, match="`window` must be a positive integer"):
        oj.check_basin(plain, U, Z, window=2.5)
    with pytest.raises(TypeError, match="`margin` must be a non-negative number"):
        oj.check_basin(plain, U, Z, margin="5")
    with pytest.raises(ValueError, match=r"must be the record the result was fitted on"):
        oj.check_basin(plain, U[:300], Z[:300])
    # Records of different lengths (a fit on several): named, not NumPy's ragged-array error
    with pytest.raises(ValueError, match=r"u a list of 2 records, z a list of 2 records"):
        oj.check_basin(plain, [U, U[:300]], [Z, Z[:300]])
    # Another record of the same shape (the windows would be fitted to it and compared
    # with the result's FIT on its own): the result's simulation on it is not z +
    # residuals.
    with pytest.raises(ValueError, match=r"fitted on: the result's simulation on this `u`"):
        oj.check_basin(plain, U[::-1], Z[::-1])
    with pytest.raises(ValueError, match=r"fitted on: the result's simulation on this `u`"):
        oj.check_basin(plain, U, Z + 0.01)


def test_basin_check_holds_what_the_fit_held():
    """A parameter held in the fit stays held in the windows (freed, it would let them fit
    better for that alone: a false alarm); `fixed=` still overrides. (Windows of 50, as
    in the tests above: the freed windowed fit is their program.)"""
    held = oj.fit(MODEL, TRUTH, np.zeros(2), U, Z, fixed={"w0sq": True, "b": False})
    check = oj.check_basin(held, U, Z, window=50)
    assert float(check.windowed.theta["w0sq"]) == TRUTH["w0sq"]
    assert check.windowed.names == ("b",)
    free = oj.check_basin(held, U, Z, window=50, fixed=None)
    assert free.windowed.names == ("b", "w0sq")
    # A fit that took NaN in z as missing samples: the windows do too (they raised).
    gaps = np.array(Z)
    gaps[[7, 250]] = np.nan
    masked = oj.fit(MODEL, TRUTH, np.zeros(2), U, gaps, fixed={"w0sq": True}, missing="mask")
    check = oj.check_basin(masked, U, gaps, window=50)
    assert np.isnan(check.windowed.residuals).sum() == 2


# A first-order lag x' = a (u - x): one real eigenvalue -a.
def lag(x, u, p):
    return p["a"] * (u - x)


def _lag_data(substeps):
    model = oj.Model.from_ode(lag, DT, substeps=substeps)
    u = np.sign(np.sin(0.4 * np.arange(120)))[:, None]
    _, z = oj.simulate(model, {"a": 52.0}, np.zeros(1), u)
    return model, u, np.asarray(z)


def test_stability_warning_after_a_fit_with_too_few_substeps():
    """a = 52 with h = dt = 0.05: |lambda| h = 2.6, inside RK4's real-axis limit 2.785
    (the data simulate fine) but beyond the 2.5 margin: fit warns, naming the value."""
    model, u, z = _lag_data(1)
    with pytest.warns(RuntimeWarning, match=r"\|lambda\| h = 2\.6.*substeps=2"):
        result = oj.fit(model, {"a": 40.0}, np.zeros(1), u, z)
    assert abs(float(result.theta["a"]) - 52.0) < 1e-6


def test_check_stability_says_when_the_discretised_model_is_unstable():
    """a = 60 with h = 0.05: lambda h = -3, past RK4's real-axis limit 2.785, where its
    step multiplies the mode by R(-3) = 1.375 and the simulation grows without bound: the
    warning said the model runs "near" the limit."""
    model, u, _ = _lag_data(1)
    with pytest.warns(RuntimeWarning) as caught:
        report = oj.check_stability(model, {"a": 60.0}, np.zeros(1), u)
    text = str(caught[0].message)
    assert report.value == pytest.approx(3.0)
    assert text.startswith("the model runs past its integrator's stability limit"), text
    assert "|R(lambda h)| = 1.375, the ODE by exp(Re lambda h) = 0.04979" in text


def test_a_mode_too_stiff_for_a_complex_power_is_reported_past_the_limit():
    """a = 1e100 (a log-parameterised rate held far out): RK4's step factor at lambda h =
    -5e98 overflows a float; Python's complex power raised OverflowError out of the check
    that `fit` runs after a fit, losing the finished result. It reports past the limit."""
    model, u, _ = _lag_data(1)
    with pytest.warns(RuntimeWarning, match="the simulated states grow without bound"):
        report = oj.check_stability(model, {"a": 1e100}, np.zeros(1), u[:5])
    assert report.value == pytest.approx(5e98) and report.near_limit


@pytest.mark.parametrize("substeps, warns", [(1, True), (2, False)])
def test_check_stability(substeps, warns):
    model, u, _ = _lag_data(substeps)
    if warns:
        with pytest.warns(
            RuntimeWarning, match="^the model runs near its integrator.s stability limit"
        ):
            report = oj.check_stability(model, {"a": 52.0}, np.zeros(1), u)
    else:
        report = _no_warnings(oj.check_stability, model, {"a": 52.0}, np.zeros(1), u)
    assert report.value == pytest.approx(52.0 * DT / substeps)
    assert report.near_limit is warns and report.limit == 2.5
    assert report.eigenvalue == pytest.approx(-52.0)


def test_rk4_past_its_accurate_range_warns_that_a_faster_mode_steps_like_a_slower_one():
    """A lag x' = a (u - x) sampled with h = 0.1, the data of a = 5 (simulated finely).
    RK4's step factor R(-2.456) equals R(-0.5) = e^-0.5, so a = 24.56 fits as well as
    a = 5: the fit from a = 20 converged there, at |lambda| h = 2.46, inside the stability
    margin 2.5, without a warning. It warns now (RK4 follows the ODE up to the fold of R at
    1.596; the warning starts at 1.5), naming 2 substeps; the fit from a = 3 reaches a = 5
    (|lambda| h = 0.5) silently. Data that need a mode faster than RK4 steps at this h
    (a = 20) pull the fit to the fold itself, where it stops: a limit at the fold (1.6)
    let that fit end unwarned."""
    model = oj.Model.from_ode(lag, 0.1)
    u = np.sign(np.sin(0.2 * np.arange(300)))[:, None]
    _, z = oj.simulate(oj.Model.from_ode(lag, 0.1, substeps=10), {"a": 5.0}, np.zeros(1), u)
    z = np.asarray(z) + 0.01 * np.random.default_rng(0).standard_normal(z.shape)
    near = _no_warnings(oj.fit, model, {"a": 3.0}, np.zeros(1), u, z)
    with pytest.warns(RuntimeWarning, match=r"no longer follows the ODE.*substeps=2") as seen:
        far = oj.fit(model, {"a": 20.0}, np.zeros(1), u, z)
    assert len(seen) == 1
    assert near.success and far.success  # (both minima of the discrete model's loss)
    assert float(near.theta["a"]) == pytest.approx(5.0, abs=0.05)
    assert float(far.theta["a"]) == pytest.approx(24.56, abs=0.05)
    assert float(far.loss) == pytest.approx(float(near.loss), rel=1e-3)
    with pytest.warns(RuntimeWarning, match="no longer follows the ODE"):
        report = oj.check_stability(model, far.theta, far.x0, u)
    assert report.inaccurate and not report.near_limit
    assert report.value == pytest.approx(2.456, abs=0.01) and report.accurate_limit == 1.5
    _, z = oj.simulate(oj.Model.from_ode(lag, 0.1, substeps=10), {"a": 20.0}, np.zeros(1), u)
    z = np.asarray(z) + 0.01 * np.random.default_rng(0).standard_normal(z.shape)
    with pytest.warns(RuntimeWarning, match=r"no longer follows the ODE.*substeps=2"):
        folded = oj.fit(model, {"a": 18.0}, np.zeros(1), u, z)
    assert 15.0 < float(folded.theta["a"]) < 15.97  # (R's fold: |lambda| h = 1.596)


@pytest.mark.parametrize("substeps, warns", [(2, True), (10, False)])
def test_euler_stability_is_its_disc_not_a_radius(substeps, warns):
    """k = 900, c = 10: lambda = -5 +- 29.6j, |lambda| = 30. Under Euler with h = 0.05
    (|lambda| h = 1.5 < 2) the mode lies outside the disc |1 + lambda h| <= 1 (1.66) and
    the simulation grows while the ODE decays: the measure h |lambda|^2 / (-Re lambda)
    is 9, a warning. With h = 0.01 it is 1.8 and |1 + lambda h| = 0.95: no warning."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])

    model = oj.Model.from_ode(rhs, 0.1, method="euler", substeps=substeps)
    theta, x0, u = {"k": 900.0, "c": 10.0}, np.array([1.0, 0.0]), np.zeros((100, 1))
    if warns:
        with pytest.warns(RuntimeWarning, match=r"h \|lambda\|\^2 / \(-Re lambda\) = 9"):
            report = oj.check_stability(model, theta, x0, u)
    else:
        report = _no_warnings(oj.check_stability, model, theta, x0, u)
    h = 0.1 / substeps
    assert report.value == pytest.approx(900.0 * h / 5.0)
    assert report.near_limit is warns
    assert (abs(1 + report.eigenvalue * h) > 1) is warns


def test_euler_warns_of_an_undamped_mode_at_any_step():
    """k = 38**2, c = 0: lambda = +-38j. Euler grows the mode by |1 + lambda h| = 2.15 a
    step at h = 0.05 (6e10 in 30 steps), but its measure fell back to |lambda| h = 1.9 < 2:
    no warning, while c = 1e-3 gave 1.4e5 and a warning. An undamped mode is outside
    Euler's disc at any h: inf, and the remedy is RK4, unless Euler grows it by at most
    1 % over the record."""

    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] - th["c"] * x[1]])

    model = oj.Model.from_ode(rhs, 0.05, method="euler")
    x0, u = np.array([1.0, 0.0]), np.zeros((100, 1))
    for c in (0.0, 1e-3):
        with pytest.warns(RuntimeWarning, match="EULER") as rec:
            report = oj.check_stability(model, {"k": 38.0**2, "c": c}, x0, u)
        assert report.near_limit and abs(1 + report.eigenvalue * 0.05) > 2
    assert report.value == pytest.approx(38.0**2 * 0.05 / 5e-4, rel=1e-6)
    with pytest.warns(RuntimeWarning, match=r"= inf .*method=\"rk4\"") as rec:
        report = oj.check_stability(model, {"k": 38.0**2, "c": 0.0}, x0, u)
    assert report.value == np.inf and len(rec) == 1
    # A slow undamped mode: Euler grows it by (1 + |lambda h|^2)^(N/2) over a record's N
    # steps, 1.0005 at h = 0.001 (followed: no warning), 1.051 at h = 0.01 (named).
    slow, u = {"k": 1.0, "c": 0.0}, np.zeros((1000, 1))
    report = _no_warnings(
        oj.check_stability, oj.Model.from_ode(rhs, 0.001, method="euler"), slow, x0, u
    )
    assert report.value == pytest.approx(0.001) and report.growth is None
    with pytest.warns(RuntimeWarning, match=r"here by 1\.05 over a record"):
        report = oj.check_stability(oj.Model.from_ode(rhs, 0.01, method="euler"), slow, x0, u)
    assert report.value == np.inf and report.growth == pytest.approx(1.0001**499.5)
    integrator = oj.Model.from_ode(lambda x, u, th: th["g"] * u[:1], 0.05, method="euler")
    report = _no_warnings(oj.check_stability, integrator, {"g": 1.0}, np.zeros(1), u)
    assert not report.near_limit  # lambda = 0: neither grows nor decays


def gated(x, u, p):
    """A lag whose rate a second input multiplies by 11 where it is on."""
    return p["a"] * (1.0 + 10.0 * u[1]) * (u[0] - x)


def test_a_stiff_mode_switched_on_between_the_evenly_spaced_states_is_found():
    """A lag gated 11 times faster at 39 of 300 samples, none of them among the 32 evenly
    spaced states: the default check read 0.176 there, and a fit with h = dt (data of
    a = 2.4 from 20 substeps) converged 13 standard errors off (a = 1.76) unwarned. The
    row bound at every state finds the gated samples: |lambda| h = 11 a dt there."""
    T = 300
    evenly = set(np.unique(np.linspace(0, T - 1, 32).astype(int)).tolist())
    gate = np.array([k % 7 == 3 and k not in evenly for k in range(T)], float)
    k = np.arange(T)
    u = np.stack([np.sin(0.07 * k) + np.sign(np.sin(0.23 * k)), gate], 1)
    coarse = oj.Model.from_ode(gated, 0.1)
    with pytest.warns(RuntimeWarning, match=r"\|lambda\| h = 2\.64 .*substeps=2"):
        report = oj.check_stability(coarse, {"a": 2.4}, np.zeros(1), u)
    assert report.value == pytest.approx(2.4 * 11 * 0.1) and gate[report.sample] == 1
    _, z = oj.simulate(oj.Model.from_ode(gated, 0.1, substeps=20), {"a": 2.4}, np.zeros(1), u)
    z = np.asarray(z) + 0.001 * np.random.default_rng(0).standard_normal((T, 1))
    with pytest.warns(RuntimeWarning, match="no longer follows the ODE"):
        oj.fit(coarse, {"a": 2.0}, np.zeros(1), u, z)


def _timed_lag_data():
    """The lag sampled every 0.04 except one interval of 0.052, away from the states
    `check_stability` spaces evenly: a = 52 gives |lambda| h = 2.08 on the others and
    2.704 on that step alone."""
    intervals = np.full(119, 0.04)
    intervals[77] = 0.052
    t = np.concatenate([[0.0], np.cumsum(intervals)])
    u = np.sign(np.sin(0.4 * np.arange(120)))[:, None]
    return t, u


def test_stability_of_a_time_stamped_model_takes_each_step_its_own_h():
    """A model of time-stamped records (`dt=None`): h is each interval over its number of
    integrator steps, and the longest interval is checked even where the evenly spaced
    states miss it. Fit warns as `check_stability` does; with `max_step` the remedy
    names it."""
    t, u = _timed_lag_data()
    model = oj.Model.from_ode(lag, None)
    with pytest.warns(RuntimeWarning, match=r"h = 2\.7 with h = dt / substeps = 0\.052 / 1"):
        report = oj.check_stability(model, {"a": 52.0}, np.zeros(1), u, t=t)
    assert report.value == pytest.approx(52.0 * 0.052) and report.sample == 77
    assert (report.dt, report.substeps) == (pytest.approx(0.052), 1)
    _, z = oj.simulate(model, {"a": 52.0}, np.zeros(1), u, t=t)
    with pytest.warns(RuntimeWarning, match=r"\|lambda\| h = 2\.7.*substeps=2"):
        oj.fit(model, {"a": 40.0}, np.zeros(1), u, np.asarray(z), t=t)
    # max_step 0.03: the long interval takes 2 steps of 0.026, the others 2 of 0.02
    split = oj.Model.from_ode(lag, None, max_step=0.03, substeps=2)
    report = _no_warnings(oj.check_stability, split, {"a": 52.0}, np.zeros(1), u, t=t)
    assert report.value == pytest.approx(52.0 * 0.026) and report.substeps == 2
    # a = 65 with max_step 0.045: 0.04 in one step (2.6), the long interval in two (1.69)
    coarse = oj.Model.from_ode(lag, None, max_step=0.045, substeps=2)
    with pytest.warns(RuntimeWarning, match=r"h = 2\.6 .*max_step=0\.02\)"):
        report = oj.check_stability(coarse, {"a": 65.0}, np.zeros(1), u, t=t)
    assert report.value == pytest.approx(65.0 * 0.04) and report.max_step == 0.045


def test_the_max_step_remedy_reaches_the_limit_in_one_go():
    """A lag with lambda = -100 sampled every second, integrated with steps of 0.5:
    |lambda| h = 50, twenty times the limit. The warning used to suggest half the step
    (0.25, still ten times the limit, then 0.125, ...); it names a step that reaches RK4's
    accurate range (1.5: 0.015), and the model built with it does not warn."""
    fast = lambda x, u, th: (-x + u) / th["tau"]  # noqa: E731
    t, u, th = np.arange(20.0), np.ones((20, 1)), {"tau": 0.01}
    model = oj.Model.from_ode(fast, None, max_step=0.5, substeps=200)
    with pytest.warns(RuntimeWarning, match=r"h = 50 .*max_step=0\.015\)") as seen:
        oj.check_stability(model, th, np.zeros(1), u, t=t)
    step = float(str(seen[-1].message).split("max_step=")[1].split(")")[0])
    refined = oj.Model.from_ode(fast, None, max_step=step, substeps=200)
    _no_warnings(oj.check_stability, refined, th, np.zeros(1), u, t=t)


def test_stability_limit_of_euler_and_other_models():
    u = np.zeros((20, 1))
    euler = oj.Model.from_ode(lag, DT, method="euler")
    with pytest.warns(RuntimeWarning, match=r"EULER: stable inside \|1 \+ lambda h\| <= 1"):
        report = oj.check_stability(euler, {"a": 44.0}, np.zeros(1), u)  # 2.2 > 2
    assert report.limit == 2.0
    report = _no_warnings(oj.check_stability, euler, {"a": 36.0}, np.zeros(1), u)  # 1.8
    assert not report.near_limit
    step = oj.Model(lambda x, u, p: x - p["a"] * DT * x)  # not from_ode: no integrator known
    assert oj.check_stability(step, {"a": 52.0}, np.zeros(1), u) is None
    with pytest.raises(ValueError, match="points"):
        oj.check_stability(euler, {"a": 1.0}, np.zeros(1), u, points=0)


def test_a_diverging_simulation_is_not_given_a_100_digit_substeps_count():
    """Euler on a stiff cubic oscillator from this theta blows the states up to 1e50: the
    largest eigenvalue along the trajectory comes from there, and the warning suggested
    `substeps=19957045155542065708514...`. Far past the limit it names the divergence."""

    def rhs(x, u, p):
        return jnp.array([x[1], -p["k"] * x[0] - p["c"] * x[1] - 5.0 * x[0] ** 3])

    model = oj.Model.from_ode(rhs, 0.1, method="euler")
    with pytest.warns(RuntimeWarning, match=r"the simulation diverges") as caught:
        oj.check_stability(model, {"k": 10.0, "c": 0.5}, np.array([1.0, 0.0]), np.zeros((60, 1)))
    assert "substeps=" not in str(caught[0].message)


def test_continuation_and_basin_take_numpy_numbers():
    """`margin=np.int64(20)` was refused as "not a non-negative number" (and `factor`
    alike), while `window=np.int64(20)` was taken."""
    cont = _no_warnings(
        oj.fit_continuation, MODEL, START, np.zeros(2), U, Z, start=50, factor=np.int64(3)
    )
    assert [s.window for s in cont.stages] == [50, 150, None]
    with pytest.raises(ValueError, match="`margin` must be a non-negative number"):
        oj.check_basin(cont.result, U, Z, margin=np.float32(-1.0))


def test_each_new_window_starts_from_the_last_stage_state_at_its_start():
    """Stage k + 1's windows start from stage k's trajectories (each simulated from its
    own window's x0) read at the new starts: for windows of 50 then 120, the new windows
    at 0, 120, 240 start from window 0's x0, window 2's state 20 samples in and window
    4's state 40 samples in."""
    from types import SimpleNamespace

    from oneshot_jax.internal import continuation_window_states as _window_states

    model = oj.Model(lambda x, u, p: p["a"] * x + u)
    rng = np.random.default_rng(3)
    u = rng.standard_normal((360, 1))  # 7 windows of 50, then 3 of 120
    last = SimpleNamespace(theta={"a": 0.9}, x0=rng.standard_normal((7, 1)))
    got = _window_states(model, last, u, 50, 120)
    want = []
    for window, k in ((0, 0), (2, 20), (4, 40)):
        xs, _ = oj.simulate(
            model, last.theta, last.x0[window], u[50 * window : 50 * window + k + 1]
        )
        want.append(np.asarray(xs)[k])
    np.testing.assert_allclose(got, np.array(want), rtol=1e-14)
    np.testing.assert_array_equal(got[0], last.x0[0])


def test_held_x0_entries_of_windows_after_the_first_are_named():
    """window= with estimate_x0=[True, False] and one x0: the windows after the first
    start from a simulation with theta0, and their held velocities are theta0's: fit
    warns. fit_continuation's windowed stages estimate every window's x0 and pass
    the mask to the last stage only, which ends at the whole-record fit from the truth."""
    mask = np.array([True, False])
    with pytest.warns(UserWarning, match=r"holds x0 entries \[1\] of every window"):
        oj.fit(MODEL, START, np.zeros(2), U, Z, window=50, estimate_x0=mask)
    # (the windowed fit of test_each_stage_keeps_its_theta: its compiled program)
    _no_warnings(oj.fit, MODEL, START, np.zeros(2), U, Z, window=50)
    cont = _no_warnings(
        oj.fit_continuation, MODEL, START, np.zeros(2), U, Z, windows=(50,), estimate_x0=mask
    )
    assert not cont.result.x0_estimated[1] and cont.result.x0[1] == 0.0  # as given
    truth = oj.fit(MODEL, TRUTH, np.zeros(2), U, Z, estimate_x0=mask)
    assert cont.result.success and truth.success
    for name in TRUTH:
        assert abs(float(cont.result.theta[name]) - float(truth.theta[name])) < 1e-6


def test_basin_check_says_inconclusive_when_its_windowed_fit_fails(plain):
    """A windowed fit that did not converge bounds nothing: no bad basin shown is then no
    all-clear, and the check says so rather than answering False in silence."""
    with pytest.warns(RuntimeWarning, match="inconclusive.*max_steps_reached"):
        check = oj.check_basin(
            plain, U, Z, window=50, margin=1e4, solver=oj.LevenbergMarquardt(max_steps=2)
        )
    assert not check.bad_basin and not check.windowed.success
    assert str(check).endswith("inconclusive: the windowed fit did not converge.")


def test_held_window_states_read_off_z_are_not_called_theta0s():
    """A model that observes its whole state starts each window at its measured z: holding
    those states (estimate_x0=False) holds data, not theta0's guesses, and fit does not
    warn that they are theta0's."""
    full = oj.Model.from_ode(lambda x, u, p: jnp.stack([x[1], -p["k"] * x[0] + u[0]]), 0.1)
    u = np.random.default_rng(0).standard_normal((100, 1))
    _, z = oj.simulate(full, {"k": 4.0}, np.array([0.3, -0.2]), u)
    r = _no_warnings(
        oj.fit,
        full,
        {"k": 3.0},
        np.array([0.3, -0.2]),
        u,
        np.asarray(z),
        window=25,
        estimate_x0=False,
    )
    np.testing.assert_array_equal(r.x0[1:], np.asarray(z)[[25, 50, 75]])


def test_the_result_prints_the_parameters_in_theta0s_order(continued):
    """Each stage starts from theta0's written order (w0sq before b), not the sorted keys
    of the last stage's fitted theta, so the printout lists them as a plain fit does."""
    assert list(START) == ["w0sq", "b"]
    assert continued.result.theta_order == ("w0sq", "b")
    text = str(continued.result)
    assert text.index("  w0sq ") < text.index("  b ")
