"""The 0.2 API: solver objects and sequences, the persistent `FitResult` (pytree,
save/load, simulate), x0-only fits with every solver, the bounded history, the progress
bar, and a library that does not import its experiments.

The satellite here is the same problem as in test_fit.py (seeds 0 and 1)."""

import dataclasses
import functools
import subprocess
import sys
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest

import oneshot_jax as oj
from oneshot_jax import constraints as oc

SAT_THETA = np.array([0.0403, 0.0404, 0.0080])
SAT_W0 = np.array([9.915e-6, -1.102e-3, 1.3179e-5])
SAT_THETA0 = SAT_THETA * np.array([1.1, 0.9, 1.15])
SAT_X00 = SAT_W0 + np.array([2e-5, -1e-4, 3e-5])

# `fit(model, M, z, theta0, x0, solver="gauss_newton", constraints=positive())` of
# oneshot_jax 0.1.0 (commit 96dc177) on this data: the optimum before the API change.
V01_THETA = np.array([0.03848733316053412, 0.04076939874933451, 0.00811819874371629])
V01_X0 = np.array([-9.8075529605390327e-06, -1.1014525397598678e-03, 2.9384175593573372e-05])
V01_LOSS = 2.1419966452136643e-08
V01_STD = np.array([1.2593423687482794e-03, 1.4133928226752195e-03, 5.5477606462395796e-05])


def satellite_rhs(w, M, inertia):
    return (M - jnp.cross(w, inertia * w)) / inertia


SAT_MODEL = oj.Model.from_ode(satellite_rhs, 0.1)


@pytest.fixture(scope="module")
def sat():
    rng = np.random.default_rng(0)
    M = 1e-5 + 1e-7 * rng.standard_normal((50, 3))
    _, z = oj.simulate(SAT_MODEL, SAT_THETA, SAT_W0, M)
    z = np.asarray(z) + 1e-4 * np.random.default_rng(1).standard_normal(z.shape)
    return {"M": M, "z": z}


@pytest.fixture(scope="module")
def sat_lm(sat):
    return oj.fit(SAT_MODEL, SAT_THETA0, SAT_X00, sat["M"], sat["z"], constraints=oc.positive())


def test_default_solver_reaches_the_0_1_optimum(sat_lm):
    r = sat_lm
    assert r.success and r.solver[0]["solver"] == "LevenbergMarquardt"
    np.testing.assert_allclose(r.theta, V01_THETA, rtol=1e-8)
    np.testing.assert_allclose(r.x0, V01_X0, rtol=1e-7)
    assert float(r.loss) == pytest.approx(V01_LOSS, rel=1e-10)
    np.testing.assert_allclose(r.std, V01_STD, rtol=1e-6)


def test_solver_names_are_aliases_of_default_objects():
    from oneshot_jax.internal import as_solvers

    assert as_solvers("gauss_newton") == (oj.GaussNewton(),)
    assert as_solvers("levenberg_marquardt") == (oj.LevenbergMarquardt(),)
    assert as_solvers("adam") == (oj.Adam(),)
    assert as_solvers("lbfgs") == (oj.LBFGS(),)
    seq = as_solvers(["adam", oj.LBFGS(max_steps=7)])
    assert seq == (oj.Adam(), oj.LBFGS(max_steps=7))
    tx = optax.sgd(1e-3)
    assert isinstance(as_solvers(tx)[0], oj.Optax)
    assert isinstance(as_solvers(optx.GaussNewton(1e-6, 1e-9))[0], oj.Optimistix)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: oj.GaussNewton(rtol=-1.0), r"GaussNewton\(rtol=...\)"),
        (lambda: oj.LevenbergMarquardt(max_steps=2.5), r"LevenbergMarquardt\(max_steps=...\)"),
        (lambda: oj.Adam(lr_theta=-1e-3), r"Adam\(lr_theta=...\)"),
        (lambda: oj.Adam(strategy="magic"), r"Adam\(strategy=...\)"),
        (lambda: oj.LBFGS(memory_size=-1), r"LBFGS\(memory_size=...\)"),
        (lambda: oj.Adam(tol_loss="small"), r"Adam\(tol_loss=...\)"),
        (lambda: oj.Adam(tol_loss=float("nan")), r"Adam\(tol_loss=...\)"),
        (lambda: oj.LBFGS(tol_loss=float("inf")), r"LBFGS\(tol_loss=...\)"),
        (lambda: oj.Optax(optax.sgd(1e-3), tol_loss=True), r"Optax\(tol_loss=...\)"),
    ],
)
def test_solver_options_are_checked_when_the_object_is_made(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_numpy_scalar_options_are_numbers():
    s = oj.LevenbergMarquardt(gtol=np.float32(1e-6), rtol=np.float64(1e-9))
    assert s.settings()["gtol"] == pytest.approx(1e-6) and oj.Adam(tol_grad=np.float32(1e-9))


def test_a_nested_sequence_runs_every_solver():
    from oneshot_jax.internal import as_solvers

    seq = as_solvers([oj.Adam(), [oj.LBFGS(max_steps=7), "gauss_newton"]])
    assert seq == (oj.Adam(), oj.LBFGS(max_steps=7), oj.GaussNewton())


def test_a_sequence_says_when_an_earlier_solver_diverged(sat):
    """Adam's first step at an absolute rate of 1e-2 takes I[2] = 0.009 to the bound, where
    the loss is not finite; L-BFGS started again from the last finite point and the fit
    reported its convergence, the divergence only a NaN in the history."""
    solver = [oj.Adam(lr_theta=1e-2, max_steps=20), oj.LBFGS(max_steps=200)]
    fit = functools.partial(
        oj.fit,
        SAT_MODEL,
        x0=SAT_X00,
        u=sat["M"],
        z=sat["z"],
        constraints=oc.positive(),
        solver=solver,
    )
    with pytest.warns(RuntimeWarning, match=r"solver 1 of the 2 in the sequence \(Adam\) div"):
        r = fit(SAT_THETA0)
    assert r.stop_info["stages_diverged"] == [0]
    assert not np.all(np.isfinite(r.history.loss[r.history.stage == 0]))
    # The baseline: the same sequence (the same compiled solve) from inertias 0.3 higher,
    # which 20 Adam steps of about 1e-2 cannot take to the bound: a finite first stage,
    # no word.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = fit(SAT_THETA0 + 0.3)
    assert np.all(np.isfinite(r.history.loss[r.history.stage == 0]))
    assert "stages_diverged" not in r.stop_info


def test_optimistix_without_steps_tests_its_start(sat, sat_lm):
    fit = functools.partial(oj.fit, SAT_MODEL, sat_lm.theta, sat_lm.x0, sat["M"], sat["z"])
    bfgs = optx.BFGS(rtol=1e-8, atol=1e-12)
    at_opt = fit(solver=oj.Optimistix(bfgs, max_steps=0), constraints=oc.positive())
    assert at_opt.status == "converged" and at_opt.num_steps == 0
    assert at_opt.stop_info["first_order"] <= 1e-8


def test_solver_objects_of_the_wrong_kind_are_type_errors():
    with pytest.raises(TypeError, match=r"Optax\(transform=...\)"):
        oj.Optax("adam")
    with pytest.raises(TypeError, match=r"Optimistix\(solver=...\)"):
        oj.Optimistix(optax.adam(1e-3))
    with pytest.raises(ValueError, match="empty sequence"):
        oj.fit(SAT_MODEL, SAT_THETA0, SAT_X00, np.zeros((5, 3)), np.zeros((5, 3)), solver=[])


def test_fit_result_is_a_pytree_and_round_trips_through_save_and_load(sat_lm, tmp_path):
    r = sat_lm
    leaves = jax.tree_util.tree_leaves(r)
    assert any(isinstance(a, np.ndarray) for a in leaves)
    assert all(not isinstance(a, jax.Array) for a in leaves)  # host results: NumPy throughout
    path = r.save(tmp_path / "sat")
    assert path.suffix == ".npz"
    loaded = oj.load_result(path, model=SAT_MODEL)
    assert eqx.tree_equal(loaded, r) is True
    assert loaded.names == r.names and loaded.solver == r.solver
    assert loaded.stop_reason == r.stop_reason and loaded.message == r.message
    assert str(loaded) == str(r)
    # The file is plain NumPy: readable without oneshot_jax or pickle.
    with np.load(path, allow_pickle=False) as npz:
        assert "__meta__" in npz.files and "covariance" in npz.files


def test_save_result_is_fit_result_save(sat_lm, tmp_path):
    """`oj.save_result(r, path)` writes the file `r.save(path)` writes (the suffix added),
    and `load_result` reads it back equal field by field."""
    path = oj.save_result(sat_lm, tmp_path / "by_function")
    assert path == tmp_path / "by_function.npz"
    loaded = oj.load_result(path, model=SAT_MODEL)
    assert eqx.tree_equal(loaded, sat_lm) is True
    assert str(loaded) == str(sat_lm)
    by_method = sat_lm.save(tmp_path / "by_method.npz")
    with np.load(path, allow_pickle=False) as a, np.load(by_method, allow_pickle=False) as b:
        assert a.files == b.files
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key])


def test_a_save_that_fails_leaves_the_file_saved_before(sat_lm, tmp_path, monkeypatch):
    """A save writes a file beside the target and renames it onto it: one that fails part
    way (a full disk, an interrupt) leaves the file saved before as it was, and nothing
    beside it (the target was truncated first, and lost). A folder given as `path`, or a
    file as its folder, is refused naming `path`."""
    path = sat_lm.save(tmp_path / "fit.npz")
    before = path.read_bytes()

    def savez_cut_short(fh, **arrays):
        fh.write(b"PK\x03\x04 half an archive")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", savez_cut_short)
    with pytest.raises(OSError, match="No space left"):
        sat_lm.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before and sorted(tmp_path.iterdir()) == [path]
    assert eqx.tree_equal(oj.load_result(path, model=SAT_MODEL), sat_lm) is True

    (tmp_path / "results").mkdir()
    with pytest.raises(ValueError, match=r"`path`: '.*results' is a folder.*results/fit.npz"):
        sat_lm.save(f"{tmp_path / 'results'}/")  # (it wrote results.npz beside the folder)
    (tmp_path / "d.npz").mkdir()
    with pytest.raises(ValueError, match=r"`path`: '.*d.npz' is a folder"):
        sat_lm.save(tmp_path / "d")
    with pytest.raises(ValueError, match=r"`path`: '.*fit.npz' is a file, not a folder"):
        sat_lm.save(path / "x.npz")
    with pytest.raises(ValueError, match=r"`path`: '.*d.npz' is a folder, not a saved result"):
        oj.load_result(tmp_path / "d.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.npz", "fit.npz", "results"]


def test_save_and_load_a_dict_theta_with_starts(tmp_path):
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"][0] * u)
    u = np.ones((30, 1))
    z = np.asarray(oj.simulate(model, {"a": 0.8, "b": np.array([0.5])}, np.array([1.0]), u)[1])
    starts = {"a": np.array([0.2, 0.5, 0.9]), "b": np.array([[0.1], [0.2], [0.3]])}
    r = oj.fit(
        model,
        starts,
        np.array([1.0]),
        u,
        z,
        multistart=True,
        solver=oj.GaussNewton(),
        estimate_x0=False,
    )
    loaded = oj.load_result(r.save(tmp_path / "dict.npz"))
    # (loaded without a model, it keeps the file's record of the model for a later save)
    assert loaded.saved_model_signature is not None
    loaded = dataclasses.replace(loaded, saved_model_signature=None)
    assert eqx.tree_equal(loaded, eqx.tree_at(lambda x: x.model, r, None)) is True
    assert loaded.starts.stop_reason == r.starts.stop_reason
    for call, name in (
        (lambda: loaded.simulate(u), "simulate"),
        (lambda: loaded.predict(u, z[:5]), "predict"),
        (lambda: loaded.predict_ahead(u, z, 2, process_noise=1.0), "predict_ahead"),
        (lambda: loaded.find_equilibrium(np.zeros(1)), "find_equilibrium"),
        (lambda: loaded.linearise(np.ones(1), np.zeros(1)), "linearise"),
    ):
        with pytest.raises(ValueError, match=rf"holds no model.*`oneshot_jax\.{name}`"):
            call()
    with pytest.raises(ValueError, match=r"holds no model .*`oneshot_jax.load_result`\.$"):
        loaded.output_std(u, x0=np.ones(1))


def test_load_finds_the_suffix_and_checks_like(tmp_path):
    """`save("b")` writes b.npz (NumPy's suffix): `load_result("b")` finds it. A `like`
    with other names or sizes is refused: it would have renamed the parameters."""
    rng = np.random.default_rng(0)
    model = oj.Model(lambda x, u, th: th["a"] * x + th["b"] * u, lambda x, u, th: x)
    u = rng.standard_normal((40, 1))
    _, z = oj.simulate(model, {"a": 0.8, "b": np.array([0.5])}, np.array([1.0]), u)
    theta0 = {"a": 0.5, "b": np.array([0.3])}
    r = oj.fit(model, theta0, np.array([1.0]), u, np.asarray(z), estimate_x0=False)
    r.save(tmp_path / "b")
    loaded = oj.load_result(tmp_path / "b", like=theta0)
    assert loaded.names == r.names == ("a", "b[0]")
    with pytest.raises(ValueError, match=r"`like` names the parameters differently .*'p' in"):
        oj.load_result(tmp_path / "b", like={"p": 0.5, "q": np.array([0.3])})
    with pytest.raises(ValueError, match=r"`like`: its parameter leaf 1 has shape \(2,\)"):
        oj.load_result(tmp_path / "b", like={"a": 0.5, "b": np.zeros(2)})


@pytest.mark.filterwarnings("ignore:the Jacobian is rank-deficient")
def test_load_refuses_a_like_whose_activation_or_static_fields_differ(tmp_path):
    """A module theta's activation and static fields are not in the file: a `like` with the
    same shapes and names but another activation (or another static scale) would rebuild a
    different model silently; it is refused, naming the difference."""

    class Scaled(eqx.Module):
        net: eqx.nn.MLP
        scale: float = eqx.field(static=True)

    def step(x, u, th):
        return x + 0.1 * (u - th["c"] * x + th["r"].scale * th["r"].net(x)[0])

    def make(activation, scale):
        net = eqx.nn.MLP(1, 1, 3, 1, activation=activation, key=jax.random.PRNGKey(0))
        return {"c": 0.5, "r": Scaled(net, scale)}

    model = oj.Model(step, lambda x, u, th: x)
    theta0 = make(jax.nn.tanh, 0.1)
    u = np.sin(0.3 * np.arange(30.0))[:, None]
    _, z = oj.simulate(model, theta0, np.array([0.2]), u)
    r = oj.fit(model, theta0, np.array([0.2]), u, np.asarray(z), solver=oj.Adam(max_steps=2))
    path = r.save(tmp_path / "net")
    back = oj.load_result(path, like=make(jax.nn.tanh, 0.1), model=model)
    np.testing.assert_array_equal(back.simulate(u)[1], r.simulate(u)[1])
    with pytest.raises(
        ValueError, match=r"has theta\['r'\]\.net\.activation = function relu, the file has "
    ):
        oj.load_result(path, like=make(jax.nn.relu, 0.1))
    with pytest.raises(
        ValueError,
        match=r"has theta\['r'\]\.scale = 2\.0, the file has theta\['r'\]\.scale = 0\.1\.",
    ):
        oj.load_result(path, like=make(jax.nn.tanh, 2.0))
    # An integer array of a dict theta (an exponent) and a partial's arguments.
    model2 = oj.Model(lambda x, u, th: th["k"] * x ** th["p"][0] + u, lambda x, u, th: x)
    theta2 = {"k": 0.5, "p": np.array([1])}
    _, z2 = oj.simulate(model2, theta2, np.array([0.2]), u)
    r2 = oj.fit(model2, theta2, np.array([0.2]), u, np.asarray(z2), solver=oj.Adam(max_steps=2))
    path2 = r2.save(tmp_path / "int")
    with pytest.raises(
        ValueError, match=r"has theta\['p'\] = array\(1,\) int64 \[3\], the file has"
    ):
        oj.load_result(path2, like={"k": 0.5, "p": np.array([3])})
    leaky = functools.partial(jax.nn.leaky_relu, negative_slope=0.5)
    r3 = oj.fit(
        model, make(leaky, 0.1), np.array([0.2]), u, np.asarray(z), solver=oj.Adam(max_steps=2)
    )
    path3 = r3.save(tmp_path / "leaky")
    other = functools.partial(jax.nn.leaky_relu, negative_slope=0.01)
    with pytest.raises(ValueError, match=r"partial\(function leaky_relu, negative_slope=0\.01\)"):
        oj.load_result(path3, like=make(other, 0.1))
    oj.load_result(path3, like=make(leaky, 0.1))


def test_a_result_refuses_inputs_and_models_other_than_the_fitted_ones(sat_lm, tmp_path):
    """`simulate`/`predict` of a result check u's columns against the fitted data's (a
    transposed u simulated one sample; an extra column was ignored), and `load_result`
    checks the model against what the file records of it (a dt of 0.05 for 0.1 loaded
    and simulated with FIT -51 % in an audit)."""
    r = sat_lm
    M = np.zeros((20, 3))
    for bad, hint in ((M.T, "is it transposed?"), (np.zeros((20, 4)), "got shape (20, 4)")):
        for call in (lambda: r.simulate(bad), lambda: r.predict(bad, np.zeros((5, 3)))):
            with pytest.raises(ValueError, match=r"`u` must have n_u = 3 input columns") as e:
                call()
            assert hint in str(e.value)
    path = r.save(tmp_path / "sat")
    other = oj.Model.from_ode(satellite_rhs, SAT_MODEL.step.dt * 2)
    with pytest.raises(ValueError, match=r"`model` has model\.step\.dt = .*, the file has model"):
        oj.load_result(path, model=other)
    assert oj.load_result(path, model=SAT_MODEL).n_u == 3


def test_load_refuses_a_foreign_file(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, a=np.ones(3))
    with pytest.raises(ValueError, match="not a saved oneshot_jax FitResult"):
        oj.load_result(path)
    with pytest.raises(FileNotFoundError, match="`path`"):
        oj.load_result(tmp_path / "missing.npz")


def test_result_simulate_runs_the_fitted_model(sat, sat_lm):
    x, z = sat_lm.simulate(sat["M"])
    np.testing.assert_allclose(z - sat["z"], sat_lm.residuals, rtol=0, atol=1e-15)
    x2, _ = sat_lm.simulate(sat["M"][:10], x0=SAT_W0)
    assert x2.shape == (10, 3) and np.array_equal(x2[0], SAT_W0)


# (Gauss-Newton is the last stage of "sequence": it solves the x0-only fit there)
X0_ONLY_SOLVERS = {
    "levenberg_marquardt": lambda: oj.LevenbergMarquardt(),
    "adam": lambda: oj.Adam(lr_x0=2e-5, max_steps=3000),
    "lbfgs": lambda: oj.LBFGS(max_steps=100),
    "optimistix": lambda: oj.Optimistix(optx.LevenbergMarquardt(rtol=1e-12, atol=1e-20)),
    "sequence": lambda: [oj.Adam(lr_x0=1e-5, max_steps=100), oj.GaussNewton()],
}


@pytest.mark.parametrize("name", list(X0_ONLY_SOLVERS))
def test_estimating_x0_alone_works_with_every_solver(sat, name):
    """Every parameter fixed, x0 estimated: what a user does on new data. The reference is
    the linear least-squares solution in x0 computed here (the outputs are affine in x0
    to first order; at the optimum the GN step of our own residuals vanishes)."""
    r = oj.fit(
        SAT_MODEL,
        SAT_THETA,
        SAT_X00,
        sat["M"],
        sat["z"],
        solver=X0_ONLY_SOLVERS[name](),
        fixed=True,
    )
    assert r.names == () and r.covariance.shape == (0, 0)
    assert np.array_equal(r.theta, SAT_THETA) and np.all(r.std == 0)
    res = lambda x0: (oj.simulate(SAT_MODEL, SAT_THETA, x0, sat["M"])[1] - sat["z"]).ravel()  # noqa: E731
    J = np.asarray(jax.jacfwd(res)(jnp.asarray(r.x0)))
    step = np.linalg.lstsq(J, -np.asarray(res(jnp.asarray(r.x0))), rcond=None)[0]
    assert np.linalg.norm(step) <= 1e-6 * np.linalg.norm(r.x0), (name, step)
    # x0's covariance: sigma^2 (J^T J)^{-1} with the data residual Jacobian.
    e = np.asarray(res(jnp.asarray(r.x0)))
    cov = np.sum(e**2) / (e.size - 3) * np.linalg.inv(J.T @ J)
    assert r.x0_covariance.shape == (3, 3)
    np.testing.assert_allclose(r.x0_covariance, cov, rtol=1e-5)
    np.testing.assert_allclose(r.x0_std, np.sqrt(np.diag(cov)), rtol=1e-5)


def test_optimistix_runs_compiled_with_a_real_history_and_multistart(sat):
    starts = np.stack([SAT_THETA0, SAT_THETA * np.array([0.9, 1.1, 0.95])])
    r = oj.fit(
        SAT_MODEL,
        starts,
        SAT_X00,
        sat["M"],
        sat["z"],
        multistart=True,
        solver=oj.Optimistix(optx.LevenbergMarquardt(rtol=1e-12, atol=1e-20)),
    )
    assert r.success
    np.testing.assert_allclose(r.theta, V01_THETA, rtol=1e-7)
    h = r.history
    assert len(h) == r.num_steps + 1 >= 3
    assert np.all(np.isfinite(h.loss)) and np.all(np.isfinite(h.grad_norm))
    assert h.loss[-1] == pytest.approx(float(r.loss), rel=1e-12)
    assert h.loss[-1] < h.loss[0]
    assert r.starts.loss.shape == (2,)
    assert all(s == "converged" for s in r.starts.stop_reason)


def _sat_fit(sat, **kwargs):
    """A fit of the satellite record from the module's start."""
    return oj.fit(SAT_MODEL, SAT_THETA0, SAT_X00, sat["M"], sat["z"], **kwargs)


def test_history_is_bounded_and_evenly_thinned(sat):
    """A step budget of 10^9 allocates nothing per step: the history keeps at most
    `history` rows, evenly strided, with the final iterate last."""
    # (history=4, as in the test below: the same compiled fit, the thresholds being data)
    r = _sat_fit(
        sat,
        history=4,
        solver=oj.Adam(lr_x0=1e-5, max_steps=10**9, tol_grad=1e-6),
    )
    assert r.stop_reason == oj.RESULTS.tol_grad
    h = r.history
    assert 2 <= len(h) <= 5
    assert h.step[-1] == r.num_steps and h.step[0] == 0
    strides = np.diff(h.step[:-1])
    assert np.all(strides == strides[0])  # one stride, a power of two
    assert strides[0] & (strides[0] - 1) == 0
    assert h.grad_norm[-1] < 1e-6 <= h.grad_norm[-2]


@pytest.mark.parametrize("steps, kept", [(13, [0, 4, 8, 12, 13]), (7, [0, 2, 4, 6, 7])])
def test_history_thins_only_when_a_row_is_due(sat, steps, kept):
    """A full buffer is thinned when the next row comes, not as it fills: a run that ends
    there keeps every row (13 steps with `history=4` kept steps 0, 8 and 13; 999 steps
    with the default 1000 kept 501 rows)."""
    r = _sat_fit(
        sat,
        history=4,
        solver=oj.Adam(lr_x0=1e-5, max_steps=steps, gtol=0.0),
    )
    assert r.num_steps == steps
    assert list(r.history.step) == kept


def test_history_of_a_large_theta_keeps_fewer_rows():
    """The history's rows are copies of theta: 1000 rows of a network of 66.8k weights took
    0.5 GB (1e6 weights: 8 GB), whatever the step budget. Its rows now take at most 64 MiB:
    20000 entries keep 418 rows (the record thinned sooner), not the 601 iterates of 600
    steps."""
    w = np.full(20000, 1e-4)
    model = oj.Model(lambda x, u, th: 0.5 * x + jnp.sum(th["w"]) * u)
    u = np.random.default_rng(0).standard_normal((20, 1))
    _, z = oj.simulate(model, {"w": 2 * w}, np.zeros(1), u)
    r = oj.fit(
        model,
        {"w": w},
        np.zeros(1),
        u,
        np.asarray(z),
        estimate_x0=False,
        covariance=None,
        solver=oj.Adam(lr_theta=1e-9, max_steps=600, gtol=0.0),
    )
    assert r.num_steps == 600
    assert r.history.loss.shape[0] <= 419  # (418 rows and the final iterate, at most)
    assert r.history.step[-1] == 600


def test_history_takes_numpy_and_integral_counts_and_refuses_others(sat):
    """`history` reads a NumPy integer and an integral float as the count they hold, as
    every other count of the library does (they were refused as not integers)."""
    solver = oj.Adam(lr_x0=1e-5, max_steps=7, gtol=0.0)
    want = _sat_fit(sat, history=4, solver=solver)
    for history in (np.int64(4), 4.0):
        r = _sat_fit(sat, history=history, solver=solver)
        assert list(r.history.step) == list(want.history.step) == [0, 2, 4, 6, 7]
    for bad in (3, True, 2.5, 0, "4"):
        with pytest.raises(ValueError, match="`history` must be an even integer >= 2"):
            _sat_fit(sat, history=bad, solver=solver)


def test_progress_bar_shows_the_loss(sat, capsys):
    _sat_fit(
        sat,
        progress=oj.TqdmProgress(1),
        solver=oj.Adam(lr_x0=1e-5, max_steps=30),
    )
    err = capsys.readouterr().err
    assert "loss" in err and "/30" in err


def test_progress_bar_ends_where_the_fit_stopped(sat, capsys):
    """The bar's last state is the step the solver stopped at and the loss there, not the
    last multiple of `refresh_steps` (it closed at 10/300 with the loss of step 10 for a
    fit that stopped at step 15)."""
    r = _sat_fit(
        sat,
        progress=oj.TqdmProgress(10),
        solver=oj.LevenbergMarquardt(max_steps=300),
    )
    assert r.success and r.num_steps % 10 != 0
    last = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()[-1]
    assert f" {r.num_steps}/300 " in last and f"loss {float(r.loss):.6e}" in last, last


def test_library_does_not_import_experiments_or_their_dependencies():
    """Nor SciPy (0.1 s of the import; metrics' normal quantile is the standard
    library's, datasets import scipy.io where they read a .mat file)."""
    code = (
        "import sys, oneshot_jax; "
        "names = ('experiments', 'hydra', 'omegaconf', 'matplotlib', 'scipy'); "
        "print([m for m in names if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_load_refuses_a_model_of_another_structure(tmp_path):
    """A model that does not fit the saved result (another number of outputs, another
    state, a parameter the saved theta lacks) is refused by `load_result(model=)`, naming
    the difference; the fitted model, and a timed one, load."""

    def step(x, u, th):
        return jnp.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * (u[0] - th["k"] * x[0])])

    model = oj.Model(step, lambda x, u, th: x[:1])
    u = np.random.default_rng(0).standard_normal((40, 1))
    _, z = oj.simulate(model, {"k": 2.0}, np.array([1.0, 0.0]), u)
    path = oj.fit(model, {"k": 1.5}, np.array([1.0, 0.0]), u, np.asarray(z)).save(tmp_path / "r")
    assert oj.load_result(path, model=model).theta["k"] == oj.load_result(path).theta["k"]
    with pytest.raises(ValueError, match=r"outputs of shape \(2,\), the saved residuals have 1"):
        oj.load_result(path, model=oj.Model(step))
    three = oj.Model(
        lambda x, u, th: jnp.concatenate([step(x, u, th), x[:1]]), lambda x, u, th: x[:1]
    )
    with pytest.raises(ValueError, match=r"state of shape \(3,\), the saved x0 has \(2,\)"):
        oj.load_result(path, model=three)
    other = oj.Model(lambda x, u, th: step(x, u, th) * th["c"], lambda x, u, th: x[:1])
    with pytest.raises(ValueError, match=r"does not run with the saved result's theta.*KeyError"):
        oj.load_result(path, model=other)
    timed = oj.Model.from_ode(lambda x, u, th: -th["a"] * x + u, dt=None)
    t = np.arange(30) * 0.1
    _, zt = oj.simulate(timed, {"a": 1.0}, np.ones(1), u[:30], t=t)
    fitted = oj.fit(timed, {"a": 0.5}, np.ones(1), u[:30], np.asarray(zt), t=t)
    loaded = oj.load_result(fitted.save(tmp_path / "t"), model=timed)
    assert loaded.theta["a"] == fitted.theta["a"]


def test_a_loaded_result_saved_again_keeps_the_model_check(tmp_path):
    """A result loaded without `model=` and saved again keeps the file's record of the
    fitted model: loading the second file with another model is refused as the first;
    the results of the drivers that are not saved whole say what to save."""
    model = oj.Model.from_ode(lambda x, u, th: -th["a"] * x + u, 0.1)
    other = oj.Model.from_ode(lambda x, u, th: -th["a"] * x + u, 0.5)
    u = np.random.default_rng(0).standard_normal((40, 1))
    _, z = oj.simulate(model, {"a": 1.0}, np.ones(1), u)
    r = oj.fit(model, {"a": 0.5}, np.ones(1), u, np.asarray(z))
    again = oj.load_result(r.save(tmp_path / "a.npz")).save(tmp_path / "b.npz")
    for path in (tmp_path / "a.npz", again):
        with pytest.raises(
            ValueError, match="model.step.dt = 0.5, the file has model.step.dt = 0.1"
        ):
            oj.load_result(path, model=other)
    assert oj.load_result(again, model=model).theta["a"] == r.theta["a"]
    with pytest.raises(ValueError, match=r"saved theta 1: pass a theta of the fitted structure"):
        oj.load_result(again, like={"a": 0.5, "b": 1.0})
    c = oj.fit_continuation(model, {"a": 0.5}, np.ones(1), u, np.asarray(z), windows=[10])
    with pytest.raises(TypeError, match=r"Continuation is not saved whole: save its `.result`"):
        oj.save_result(c, tmp_path / "c.npz")
