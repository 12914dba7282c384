"""`fit(window=oj.Windows(...))`: some of a record's windows (every k-th, a number spread
over the record, given starts), `FitResult.window_starts`, and the whole-record
simulation of a windowed result from the window at sample 0."""

import jax.numpy as jnp
import numpy as np
import pytest

import oneshot_jax as oj

DT, T = 0.05, 400


def _rhs(x, u, th):
    return jnp.array([x[1], -th["k"] * x[0] - th["c"] * x[1] + u[0]])


MODEL = oj.Model.from_ode(_rhs, DT, observe=lambda x, u, th: x[:1])  # position only
TRUTH = {"k": 4.0, "c": 0.5}


def _record():
    rng = np.random.default_rng(0)
    u = np.repeat(rng.normal(0.0, 1.0, T // 10), 10)[:, None]
    x0 = np.array([0.3, -0.2])
    _, z = oj.simulate(MODEL, TRUTH, x0, u)
    return u, np.asarray(z) + 0.01 * rng.normal(size=(T, 1)), x0


# (the first three cases fit 4 windows of 50 samples each, at starts that are data of one
# compiled fit: they compile once)
@pytest.mark.parametrize(
    "windows, expected",
    [
        (oj.Windows(50, every=2), [0, 100, 200, 300]),
        # 4 of the 8 windows spread: windows 0, 7/3, 14/3 and 7, rounded
        (oj.Windows(50, count=4), [0, 100, 250, 350]),
        (oj.Windows(50, starts=[0, 30, 170, 340]), [0, 30, 170, 340]),  # overlapping
        (100, [0, 100, 200, 300]),  # an integer: consecutive windows
    ],
)
def test_subsets_of_windows(windows, expected):
    u, z, x0 = _record()
    if len(expected) == 4 and expected[1] == 30:
        # 0-50 and 30-80 share 20 samples: 200 rows over 180 samples.
        # (the standard errors are off by amounts that differ between parameters, in
        # either direction: not by one factor sqrt(1.11))
        with pytest.warns(UserWarning, match=r"up to 2 windows \(1\.11 on average\).*too large"):
            res = oj.fit(MODEL, {"k": 3.0, "c": 0.3}, x0, u, z, window=windows)
    else:
        res = oj.fit(MODEL, {"k": 3.0, "c": 0.3}, x0, u, z, window=windows)
    assert res.success
    np.testing.assert_array_equal(res.window_starts, expected)
    assert res.x0.shape == (len(expected), 2)
    for k in TRUTH:
        assert abs(res.theta[k] - TRUTH[k]) < 0.05 * TRUTH[k]
    # The fitted windows are those samples: the loss over them, sliced by hand.
    L = windows.length if isinstance(windows, oj.Windows) else windows
    idx = np.asarray(expected)[:, None] + np.arange(L)
    C = oj.loss(MODEL, res.theta, res.x0, u[idx], z[idx])
    np.testing.assert_allclose(res.loss, C, rtol=1e-10)
    # The whole record starts from the window at sample 0.
    x, _ = res.simulate(u)
    np.testing.assert_allclose(x[0], res.x0[0], rtol=0, atol=0)


def test_no_window_at_zero_asks_for_x0(tmp_path):
    u, z, x0 = _record()
    # (4 windows of 50, as in test_subsets_of_windows: the same compiled fit)
    starts = [20, 120, 200, 300]
    res = oj.fit(MODEL, {"k": 3.0, "c": 0.3}, x0, u, z, window=oj.Windows(50, starts=starts))
    np.testing.assert_array_equal(res.window_starts, starts)
    with pytest.raises(ValueError, match="none at 0"):
        res.simulate(u)
    x, _ = res.simulate(u[20:], x0=res.x0[0])
    assert np.all(np.isfinite(x))
    path = res.save(tmp_path / "w.npz")
    np.testing.assert_array_equal(oj.load_result(path).window_starts, starts)


def test_windows_checks():
    with pytest.raises(ValueError, match="length"):
        oj.Windows(0)
    with pytest.raises(ValueError, match="every"):
        oj.Windows(10, every=0)
    with pytest.raises(ValueError, match="combine"):
        oj.Windows(10, starts=[0, 10], every=2)
    with pytest.raises(ValueError, match=r"`Windows\(count=...\)` does not combine with `every`"):
        oj.Windows(50, every=2, count=6)  # gave 3 windows, not 6
    with pytest.raises(ValueError, match="increasing"):
        oj.Windows(10, starts=[10, 0])
    u, z, x0 = _record()
    with pytest.raises(ValueError, match="ends after"):
        oj.fit(MODEL, TRUTH, x0, u, z, window=oj.Windows(50, starts=[0, 380]))
    with pytest.raises(ValueError, match="holds only"):
        oj.fit(MODEL, TRUTH, x0, u, z, window=oj.Windows(100, count=5))
    # A stride in samples given as `every`: 4 windows of 100, every 4th keeps one.
    with pytest.raises(ValueError, match=r"holds only 4 windows .*counts windows, not samples"):
        oj.fit(MODEL, TRUTH, x0, u, z, window=oj.Windows(100, every=4))
    np.testing.assert_array_equal(oj.Windows(100, every=3).first_samples(T), [0, 300])
    # Whole numbers as floats, as `fit(window=50.0)` takes them (they were refused).
    assert oj.Windows(50, starts=[0.0, 100.0]).starts == (0, 100)
    with pytest.raises(ValueError, match="sample indices"):
        oj.Windows(50, starts=[0.0, 100.5])
    # `Windows(length)` alone is the integer's windows, and says so of the samples past
    # the last window as the integer does (it dropped them without a word). (4 windows of
    # 100, as in test_subsets_of_windows: the same compiled fit)
    u2, z2 = np.concatenate([u, u[:30]]), np.concatenate([z, z[:30]])
    with pytest.warns(UserWarning, match="the last 30 samples do not fill a window"):
        res = oj.fit(MODEL, {"k": 3.0, "c": 0.3}, x0, u2, z2, window=oj.Windows(100))
    np.testing.assert_array_equal(res.window_starts, [0, 100, 200, 300])


@pytest.mark.parametrize("length", [1, 2])
def test_windows_no_longer_than_their_x0_are_refused(length):
    """A window of 2 position samples is fitted exactly by its own (position, velocity):
    such a fit returned `zero_residual` (success) with theta at its start."""
    u, z, x0 = _record()
    with pytest.raises(ValueError, match=r"`window` of \d samples holds \d output values per "):
        oj.fit(MODEL, {"k": 3.0, "c": 0.3}, x0, u, z, window=length)
    # Fewer x0 entries estimated, or longer windows: theta is determined.
    oj.fit(MODEL, TRUTH, x0, u, z, window=2, estimate_x0=np.array([True, False]))
    oj.fit(MODEL, TRUTH, x0, u, z, window=3)
    # A whole record as short (it returned `converged`, success, with theta at its start),
    # and records each as short, alike
    with pytest.raises(ValueError, match=rf"the record of {length} samples? holds {length} "):
        oj.fit(MODEL, {"k": 3.0, "c": 0.3}, x0, u[:length], z[:length])
    with pytest.raises(ValueError, match=r"each record of .* no more than the 2 entries of its"):
        oj.fit(
            MODEL, TRUTH, np.stack([x0, x0]), np.stack([u[:length]] * 2), np.stack([z[:length]] * 2)
        )
    oj.fit(MODEL, TRUTH, x0, u[: length + 1], z[: length + 1], estimate_x0=np.array([True, False]))


def test_window_with_an_x0_per_start_is_refused_by_name():
    def rhs(x, u, th):
        return jnp.stack([x[1], -th["k"] * x[0] + u[0]])

    model = oj.Model.from_ode(rhs, 0.05, observe=lambda x, u, th: x[:1])
    u = np.zeros((100, 1))
    z = np.zeros((100, 1))
    with pytest.raises(ValueError, match="`window` with per-start x0 is not supported"):
        oj.fit(
            model,
            {"k": np.array([1.0, 2.0])},
            np.zeros((2, 2, 2)),
            u,
            z,
            multistart=True,
            window=50,
        )


def test_multistart_windows_take_their_states_from_a_start_that_stays_finite():
    """With `multistart` and `window`, the windows' starting states come from the first
    start whose simulation stays finite over the windows: a blowing-up first start does
    not refuse the whole fit, and the order of the starts does not matter."""
    u, z, x0 = _record()
    good, bad = {"k": 3.0, "c": 0.4}, {"k": -4000.0, "c": -600.0}
    for first, second in ((bad, good), (good, bad)):
        theta0 = {key: np.array([first[key], second[key]]) for key in good}
        r = oj.fit(MODEL, theta0, x0, u, z, multistart=True, window=100)
        assert r.success and sorted(r.starts.stop_reason)[0] == "converged"
        assert abs(float(r.theta["k"]) - 4.0) < 0.05
    theta0 = {key: np.array([bad[key], bad[key]]) for key in good}
    with pytest.raises(ValueError, match="every one of the 2 starts"):
        oj.fit(MODEL, theta0, x0, u, z, multistart=True, window=100)


def test_a_held_state_missing_at_a_windows_first_sample_is_refused():
    """A model that observes its whole state reads each window's x0 from its first sample
    of z. Where that sample is missing in an entry `estimate_x0` holds, the entry was held
    at 0 in silence (a success at a loss 200 times the clean fit's); estimated entries
    start there and move (the fit is the clean one's)."""
    model = oj.Model(lambda x, u, th: th["A"] @ x + th["B"] @ u)
    rng = np.random.default_rng(0)
    A, B = np.array([[0.9, 0.2], [-0.2, 0.9]]), np.array([[0.0], [0.5]])
    u = rng.standard_normal((200, 1))
    _, z = oj.simulate(model, {"A": A, "B": B}, np.array([1.0, -0.5]), u)
    z = np.asarray(z) + 0.02 * rng.standard_normal((200, 2))
    gap = z.copy()
    gap[50, 1] = np.nan
    th0 = {"A": np.array([[0.8, 0.1], [-0.1, 0.8]]), "B": np.array([[0.1], [0.3]])}
    kw = dict(window=50, missing="mask")
    with pytest.raises(ValueError, match=r"`estimate_x0` holds x0 entries \[1\] of the windows"):
        oj.fit(model, th0, z[0], u, gap, estimate_x0=np.array([True, False]), **kw)
    both = oj.fit(model, th0, z[0], u, gap, **kw)
    clean = oj.fit(model, th0, z[0], u, z, **kw)
    assert both.success and float(both.loss) < 1.5 * float(clean.loss)


def test_an_x0_per_window_of_the_wrong_state_size_names_its_shape():
    """`x0` of shape (n_windows, 3) for a model of 2 states: the error of the model's call
    said "from `x0` of shape (3,)", the shape of the row it was called with."""
    u, z, _ = _record()
    with pytest.raises(ValueError, match=r"`x0` \(of shape \(4, 3\), one initial state \(3,\) per"):
        oj.fit(MODEL, TRUTH, np.zeros((4, 3)), u, z, window=10)
    step = oj.Model(lambda x, u, th: th["A"] @ x, lambda x, u, th: x[:1])
    with pytest.raises(ValueError, match=r"a row of `x0` of shape \(4, 3\), one initial state per"):
        oj.fit(step, {"A": 0.9 * np.eye(2)}, np.zeros((4, 3)), u, z, window=10)
