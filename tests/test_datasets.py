"""oneshot_jax.datasets: the loaders' shapes, values, search order and error messages.

Tests on the real benchmark files skip, naming the files, when they are not found (they
are not in the repository: they are looked up in $ONESHOT_JAX_DATA, then ../shared/data,
which ONESHOT_JAX_HIDE_DATA=1 hides); the bad-input tests use temporary files and always
run.
"""

import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from helpers import benchmark_or_skip

import oneshot_jax as oj
from oneshot_jax import datasets as ds
from oneshot_jax.internal import locations_module


def _emps_or_skip():
    return benchmark_or_skip(ds.load_emps)


def _tanks_or_skip():
    return benchmark_or_skip(ds.load_cascaded_tanks)


def _emps_dict(n=50, pulses=False):
    t = np.arange(n)[:, None] * 1e-3
    d = {
        "t": t,
        "qm": np.sin(t),
        "qg": np.sin(t),
        "vir": np.cos(t),
        "kp": np.array([[160.18]]),
        "kv": np.array([[243.45]]),
        "gtau": np.array([[35.15]]),
    }
    if pulses:
        d["pulses_N"] = np.zeros((n, 1), np.uint8)
    return d


def _write_emps(folder, est=None, val=None):
    folder.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(folder / "DATA_EMPS.mat", est if est is not None else _emps_dict())
    scipy.io.savemat(
        folder / "DATA_EMPS_PULSES.mat", val if val is not None else _emps_dict(pulses=True)
    )
    return folder


def _write_csv(file, text):
    file.parent.mkdir(parents=True, exist_ok=True)
    file.write_text(text)
    return file


GOOD_CSV = (
    '"uEst","uVal","yEst","yVal","Ts",\n1,2,3,4,4,\n1.5,2.5,3.5,4.5,,\n2,3,4,5,,\n'
    + "".join(f"{k},{k + 1},{k + 2},{k + 3},,\n" for k in (3, 4, 5, 6))
)


def test_exposed_from_package():
    assert oj.datasets is ds
    assert callable(oj.datasets.load_emps) and callable(oj.datasets.load_cascaded_tanks)


# ----------------------------------------------------------------------- real files


def test_emps_shapes_and_values():
    d = _emps_or_skip()
    for rec in (d.estimation, d.validation):
        assert len(rec) == 24_841
        for a in (rec.t, rec.qm, rec.qg, rec.vir, rec.pulses):
            assert a.shape == (24_841,) and a.dtype == np.float64
        assert np.all(np.diff(rec.t) > 0)
        assert 0.0 <= rec.qm.max() < 0.3  # metres: the stroke is about 0.25 m
    assert d.kp == pytest.approx(160.18)
    assert d.kv == pytest.approx(243.45)
    assert d.gtau == pytest.approx(35.15, abs=0.01)
    assert d.Ts == 1e-3  # 1 kHz (the spacings of t carry round-off: median 0.99998 ms)
    assert not d.estimation.pulses.any()
    assert set(np.unique(d.validation.pulses)) == {0.0, 5.0}
    # The recorded force command is the benchmark's PD law on the recorded positions.
    qm, rec = d.estimation.qm, d.estimation
    nu = d.kp * d.kv * (rec.qg[2:] - qm[2:]) - d.kv * (qm[2:] - qm[:-2]) / (2 * d.Ts)
    assert np.sqrt(np.mean((nu - rec.vir[2:]) ** 2)) < 0.01


def test_tanks_shapes_and_values():
    d = _tanks_or_skip()
    for a in (d.u_est, d.y_est, d.u_val, d.y_val, d.t):
        assert a.shape == (1024,) and a.dtype == np.float64
    assert d.Ts == 4.0
    assert d.t[-1] == pytest.approx(4.0 * 1023)
    assert d.u_est[0] == pytest.approx(3.2567) and d.y_val[0] == pytest.approx(4.9728)
    assert d.y_est.max() == pytest.approx(10.0) and d.y_val.max() == pytest.approx(10.0)


def test_explicit_paths_and_env_var(tmp_path, monkeypatch):
    d = _tanks_or_skip()
    # The CSV itself, its folder, and a root with a cascaded_tanks/ subfolder.
    root = tmp_path / "root"
    (root / "cascaded_tanks").mkdir(parents=True)
    shutil.copy(d.file, root / "cascaded_tanks" / "dataBenchmark.csv")
    for p in (
        root / "cascaded_tanks" / "dataBenchmark.csv",
        root / "cascaded_tanks",
        root,
        str(root),
    ):
        np.testing.assert_array_equal(ds.load_cascaded_tanks(p).y_val, d.y_val)
    monkeypatch.setenv(ds.ENV_VAR, str(root))
    assert ds.default_data_dirs()[0] == root
    assert ds.load_cascaded_tanks().file == root / "cascaded_tanks" / "dataBenchmark.csv"


def test_a_package_installed_right_under_the_root_searches_its_other_folders(monkeypatch):
    """Installed as /oneshot_jax (a container's copy), the package has no checkout folder
    three levels up to look beside: the working directory's and the cache's are searched."""
    monkeypatch.delenv(ds.HIDE_ENV_VAR, raising=False)
    monkeypatch.setattr(locations_module, "__file__", "/oneshot_jax/datasets/_locations.py")
    monkeypatch.setenv(ds.ENV_VAR, "/nowhere/data")
    assert ds.default_data_dirs()[0] == Path("/nowhere/data")


def test_emps_from_env_var(tmp_path, monkeypatch):
    folder = _write_emps(tmp_path / "emps")
    monkeypatch.setenv(ds.ENV_VAR, str(tmp_path))
    d = ds.load_emps()
    assert d.estimation.file == folder / "DATA_EMPS.mat"
    assert len(d.validation) == 50 and d.Ts == pytest.approx(1e-3)


def test_emps_sampling_time_is_the_records_own(tmp_path):
    """A record in EMPS's format at another rate: Ts was rounded to 6 decimals (1/3000 s
    read 0.000333, 1e-3 off; 2.5e-7 s read 0, refused by the views as no sampling time)."""
    for i, dt in enumerate((1 / 3000, 2.5e-7)):
        est, val = _emps_dict(), _emps_dict(pulses=True)
        for d in (est, val):
            d["t"] = d["t"] / 1e-3 * dt
        data = ds.load_emps(_write_emps(tmp_path / str(i), est, val))
        assert data.Ts == pytest.approx(dt, rel=1e-9)
        assert data.test.Ts == data.Ts


def test_an_env_var_that_names_no_folder_is_an_error(tmp_path, monkeypatch):
    """A mistyped $ONESHOT_JAX_DATA was skipped in silence (the files came from elsewhere)."""
    _write_emps(tmp_path / "emps")
    monkeypatch.setenv(ds.ENV_VAR, str(tmp_path / "typo"))
    with pytest.raises(
        ds.DatasetNotFoundError, match=r"\$ONESHOT_JAX_DATA=.*typo.* is not a folder"
    ):
        ds.load_emps()
    assert ds.load_emps(tmp_path).Ts == pytest.approx(1e-3)  # path= is searched first


def test_emps_records_at_different_sampling_times_are_refused(tmp_path):
    val = _emps_dict(pulses=True)
    val["t"] = val["t"] * 2  # every 2 ms
    _write_emps(tmp_path / "emps", val=val)
    with pytest.raises(
        ds.DatasetFormatError, match=r"DATA_EMPS_PULSES\.mat: sampled every 0\.002 s but"
    ):
        ds.load_emps(tmp_path)


# ----------------------------------------------------------------------- bad input


def test_missing_files_say_where_to_get_them(tmp_path):
    with pytest.raises(
        ds.DatasetNotFoundError, match=r"(?s)DATA_EMPS\.mat.*nonlinearbenchmark\.org"
    ) as e:
        ds.load_emps(tmp_path)
    assert str(tmp_path) in str(e.value) and ds.ENV_VAR in str(e.value)
    assert isinstance(e.value, FileNotFoundError)
    with pytest.raises(
        ds.DatasetNotFoundError, match=r"(?s)dataBenchmark\.csv.*nonlinearbenchmark\.org"
    ) as e:
        ds.load_cascaded_tanks(tmp_path / "nowhere")
    # A path that does not exist is named first (a typo), not searched silently as a folder.
    assert str(e.value).startswith(f"path={str(tmp_path / 'nowhere')!r} does not exist.")
    with pytest.raises(ds.DatasetNotFoundError) as e:
        ds.load_emps(tmp_path)
    assert "does not exist" not in str(e.value)
    # A file of another name given as `path`: the loader reads the official names only.
    scipy.io.savemat(tmp_path / "my_emps.mat", _emps_dict())
    with pytest.raises(ds.DatasetNotFoundError) as e:
        ds.load_emps(tmp_path / "my_emps.mat")
    assert str(e.value).startswith(
        f"path={str(tmp_path / 'my_emps.mat')!r} is a file the loader does not read: it "
        "reads DATA_EMPS.mat and DATA_EMPS_PULSES.mat by these names"
    )


def test_emps_half_a_data_set(tmp_path):
    scipy.io.savemat(tmp_path / "DATA_EMPS.mat", _emps_dict())
    with pytest.raises(ds.DatasetNotFoundError, match=r"missing DATA_EMPS_PULSES\.mat"):
        ds.load_emps(tmp_path)


def test_emps_missing_variable_names_file_and_variables(tmp_path):
    bad = _emps_dict()
    del bad["qm"]
    _write_emps(tmp_path, est=bad)
    with pytest.raises(ds.DatasetFormatError) as e:
        ds.load_emps(tmp_path)
    msg = str(e.value)
    assert "DATA_EMPS.mat" in msg and "missing variable(s) qm" in msg
    assert "t, qm, qg, vir" in msg and "kp, kv, gtau" in msg
    assert isinstance(e.value, ValueError)


def test_emps_validation_without_pulses(tmp_path):
    _write_emps(tmp_path, val=_emps_dict(pulses=False))
    with pytest.raises(ds.DatasetFormatError, match=r"DATA_EMPS_PULSES\.mat.*pulses_N"):
        ds.load_emps(tmp_path)


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda d: d.update(qg=d["qg"][:-1]), r"'qg' has 49 samples but 't' has 50"),
        (lambda d: d.update(kp=np.ones((2, 1))), r"'kp' must be a numeric scalar"),
        (lambda d: d.update(vir=np.ones((50, 2))), r"'vir' must be a vector"),
        (lambda d: d.update(t=d["t"][::-1]), r"'t' .* strictly increasing"),
        (lambda d: d["qm"].__setitem__((3, 0), np.nan), r"'qm' contains NaN"),
        (
            lambda d: d.update(t=np.concatenate([d["t"][:20], d["t"][20:] + 0.5])),
            r"'t' .* not uniformly sampled: t\[20\] - t\[19\] = 0\.501 s against a median "
            r"spacing of 0\.001 s",
        ),
    ],
)
def test_emps_malformed_variables(tmp_path, change, pattern):
    bad = _emps_dict()
    change(bad)
    _write_emps(tmp_path, est=bad)
    with pytest.raises(ds.DatasetFormatError, match=pattern) as e:
        ds.load_emps(tmp_path)
    assert "DATA_EMPS.mat" in str(e.value)


def test_emps_not_a_mat_file(tmp_path):
    _write_emps(tmp_path)
    (tmp_path / "DATA_EMPS_PULSES.mat").write_bytes(b"this is not a MATLAB file at all" * 8)
    with pytest.raises(
        ds.DatasetFormatError, match=r"DATA_EMPS_PULSES\.mat.*not a readable MATLAB"
    ):
        ds.load_emps(tmp_path)


def test_emps_inconsistent_controller(tmp_path):
    val = _emps_dict(pulses=True)
    val["kp"] = np.array([[100.0]])
    _write_emps(tmp_path, val=val)
    with pytest.raises(ds.DatasetFormatError, match=r"'kp' differs"):
        ds.load_emps(tmp_path)


def test_emps_shortest_validation_record_has_a_test_view(tmp_path):
    # The test view keeps 20 outputs for x0 and the protocol scores at least two more: a
    # 21-sample file loaded, and its test view then failed naming no file.
    est = _emps_dict()
    with pytest.raises(ds.DatasetFormatError, match=r"DATA_EMPS_PULSES\.mat: .* 21 samples.* 22"):
        ds.load_emps(_write_emps(tmp_path / "a", est, _emps_dict(21, pulses=True)))
    with pytest.warns(UserWarning, match=r"has 22 samples"):
        d = ds.load_emps(_write_emps(tmp_path / "b", est, _emps_dict(22, pulses=True)))
    assert d.test.n == 20 and len(d.test) == 22


def test_tanks_good_small_file(tmp_path):
    # (a record that is not the official length loads, with a warning: a file cut short
    # at a line boundary loaded silently)
    with pytest.warns(UserWarning, match=r"has 7 samples, the official file 1024"):
        d = ds.load_cascaded_tanks(_write_csv(tmp_path / "dataBenchmark.csv", GOOD_CSV))
    np.testing.assert_array_equal(d.u_est, [1, 1.5, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(d.y_val, [4, 4.5, 5, 6, 7, 8, 9])
    assert d.Ts == 4.0


@pytest.mark.parametrize(
    "text, pattern",
    [
        ('"uEst","uVal","yEst","Ts"\n1,2,3,4\n1,2,3,\n', r"missing column\(s\) yVal"),
        (
            '"uEst","uVal","yEst","yVal","Ts"\n1,2,3,4,4\n1,x,3,4,\n',
            r"line 3: column 'uVal' holds 'x'",
        ),
        (
            '"uEst","uVal","yEst","yVal","Ts"\n1,2,3,4,4\n1,2,3\n',
            r"line 3: column 'yVal' holds '<missing>'",
        ),
        (
            '"uEst","uVal","yEst","yVal","Ts"\n1,2,3,4,\n1,2,3,4,\n',
            r"column 'Ts' must hold the sampling time",
        ),
        (
            '"uEst","uVal","yEst","yVal","Ts"\n1,2,3,4,-4\n1,2,3,4,\n',
            r"not a positive sampling time",
        ),
        ("", r"empty file"),
    ],
)
def test_tanks_malformed_csv(tmp_path, text, pattern):
    f = _write_csv(tmp_path / "dataBenchmark.csv", text)
    with pytest.raises(ds.DatasetFormatError, match=pattern) as e:
        ds.load_cascaded_tanks(f)
    assert "dataBenchmark.csv" in str(e.value)


@pytest.mark.parametrize("suffix", ["mat", "csv"])
def test_tanks_refuses_complex_variables_and_duplicate_columns(tmp_path, suffix):
    """A complex .mat variable loaded with NumPy's ComplexWarning (the imaginary part
    dropped); a CSV column named twice loaded silently (the first one read)."""
    if suffix == "mat":
        col = np.arange(6.0)[:, None]
        mat = {k: col for k in ("uVal", "yEst", "yVal")} | {"Ts": np.array([[4.0]])}
        mat["uEst"] = col + 1j
        file = tmp_path / "dataBenchmark.mat"
        scipy.io.savemat(file, mat)
        pattern = r"dataBenchmark\.mat: variable 'uEst' must be real"
    else:
        text = "uEst,uEst,uVal,yEst,yVal,Ts\n" + "".join(f"{k},{k},1,2,3,4\n" for k in range(6))
        file = _write_csv(tmp_path / "dataBenchmark.csv", text)
        pattern = r"dataBenchmark\.csv: column\(s\) uEst appear more than once"
    with pytest.raises(ds.DatasetFormatError, match=pattern):
        ds.load_cascaded_tanks(file)


@pytest.mark.parametrize(
    "load",
    [ds.load_cascaded_tanks, ds.load_emps, ds.load_silverbox, ds.load_wiener_hammerstein],
)
@pytest.mark.parametrize("argument", ["path", "cache_dir"])
def test_loaders_name_a_path_of_the_wrong_type(load, argument):
    """`path=123` was `Path`'s TypeError, which names no argument."""
    with pytest.raises(TypeError, match=f"`{argument}` must be a str or os.PathLike"):
        load(**{argument: 123})
    # (an empty string was called "not a str")
    with pytest.raises(ValueError, match=f"`{argument}` is an empty string"):
        load(**{argument: ""})


# ----------------------------------------------------------------------- protocol views


def test_emps_protocol_views_real_files():
    """Open loop: u = vir (V), y = qm (m), n = 20 on the test record."""
    d = _emps_or_skip()
    tr, te = d.train, d.test
    assert isinstance(tr, ds.Record) and isinstance(te, ds.Record)
    np.testing.assert_array_equal(tr.u, d.estimation.vir)
    np.testing.assert_array_equal(tr.y, d.estimation.qm)
    np.testing.assert_array_equal(te.u, d.validation.vir)
    np.testing.assert_array_equal(te.y, d.validation.qm)
    assert (tr.n, te.n) == (0, 20) == (0, ds.EMPS_N_INIT)
    assert tr.Ts == te.Ts == d.Ts == pytest.approx(1e-3)
    assert te.name == "test (DATA_EMPS_PULSES)"
    np.testing.assert_array_equal(te.y_head, d.validation.qm[:20])


def test_tanks_protocol_views_real_file():
    d = _tanks_or_skip()
    np.testing.assert_array_equal(d.train.u, d.u_est)
    np.testing.assert_array_equal(d.train.y, d.y_est)
    np.testing.assert_array_equal(d.test.u, d.u_val)
    np.testing.assert_array_equal(d.test.y, d.y_val)
    assert (d.train.n, d.test.n, d.test.Ts) == (0, 5, 4.0)
    np.testing.assert_array_equal(d.test.t, d.t)


def test_emps_views_match_nonlinear_benchmarks(tmp_path):
    """The package's own EMPS loader on the same files (placed where its cache looks, so
    it downloads nothing) gives the same arrays and window."""
    nb = pytest.importorskip("nonlinear_benchmarks")
    _write_emps(tmp_path / "EMPS")
    (tmp_path / "EMPS" / "EMPS.zip").write_bytes(b"")  # the package's "already downloaded"
    train, test = nb.EMPS(dir_placement=tmp_path)
    d = ds.load_emps(tmp_path / "EMPS")
    for theirs, ours in ((train, d.train), (test, d.test)):
        np.testing.assert_array_equal(theirs.u, ours.u)
        np.testing.assert_array_equal(theirs.y, ours.y)
        assert (theirs.state_initialization_window_length or 0) == ours.n
        assert theirs.sampling_time == pytest.approx(ours.Ts, rel=1e-6)
        back = ds.Record.from_nonlinear_benchmarks(theirs)
        assert back.n == ours.n and back.name == ours.name


def test_tanks_small_file_views_and_mat_fallback(tmp_path):
    rows = "".join(f"{k},{k + 1},{k + 2},{k + 3},{'4' if k == 0 else ''}\n" for k in range(8))
    big = ds.load_cascaded_tanks(
        _write_csv(tmp_path / "big.csv", GOOD_CSV.split("\n")[0] + "\n" + rows)
    )
    assert big.test.n == 5 and len(big.test) == 8
    np.testing.assert_array_equal(big.test.y_head, [3, 4, 5, 6, 7])
    short = GOOD_CSV.split("\n")
    with pytest.raises(ds.DatasetFormatError, match=r"short\.csv: .* 6 samples.* at least 7"):
        # six samples cannot hold the test view's five-sample head and the two scored
        # samples the protocol needs (`Record` refused the test view, naming no file)
        ds.load_cascaded_tanks(_write_csv(tmp_path / "short.csv", "\n".join(short[:7]) + "\n"))
    d = ds.load_cascaded_tanks(_write_csv(tmp_path / "csv" / "dataBenchmark.csv", GOOD_CSV))
    assert d.test.n == 5 and len(d.test) == 7  # the shortest file has a test view
    # The .mat version of the archive is read when there is no CSV.
    col = lambda *v: np.array(v, dtype=float)[:, None]  # noqa: E731
    mat = {
        "uEst": col(1, 1.5, 2, 3, 4, 5, 6),
        "uVal": col(2, 2.5, 3, 4, 5, 6, 7),
        "yEst": col(3, 3.5, 4, 5, 6, 7, 8),
        "yVal": col(4, 4.5, 5, 6, 7, 8, 9),
        "Ts": np.array([[4.0]]),
    }
    (tmp_path / "mat" / "cascaded_tanks").mkdir(parents=True)
    scipy.io.savemat(tmp_path / "mat" / "cascaded_tanks" / "dataBenchmark.mat", mat)
    m = ds.load_cascaded_tanks(tmp_path / "mat")
    assert m.file.name == "dataBenchmark.mat"
    for k in ("u_est", "u_val", "y_est", "y_val"):
        np.testing.assert_array_equal(getattr(m, k), getattr(d, k))
    assert m.Ts == 4.0
    del mat["Ts"]
    scipy.io.savemat(tmp_path / "mat" / "cascaded_tanks" / "dataBenchmark.mat", mat)
    with pytest.raises(ds.DatasetFormatError, match=r"dataBenchmark\.mat: missing variable"):
        ds.load_cascaded_tanks(tmp_path / "mat")


# ----------------------------------------------------------------------- Record


def test_record_basics():
    rec = ds.Record(u=[0.0, 1.0, 2.0, 3.0], y=np.arange(4), Ts=0.5, n=2, name="r")
    u, y = rec
    assert u.dtype == y.dtype == np.float64 and len(rec) == 4
    np.testing.assert_array_equal(rec.t, [0.0, 0.5, 1.0, 1.5])
    np.testing.assert_array_equal(rec.y_head, [0.0, 1.0])
    assert rec.sampling_time == 0.5 and rec.state_initialization_window_length == 2
    r2 = rec.atleast_2d()
    assert r2.u.shape == (4, 1) and r2.y.shape == (4, 1) and r2.n == 2
    assert "n=2" in repr(rec) and "'r'" in repr(rec)
    with pytest.raises(ValueError, match="discrete-time"):
        ds.Record(u=[1.0, 2.0], y=[1.0, 2.0], Ts=None).t


@pytest.mark.parametrize(
    "kwargs, error, pattern",
    [
        (dict(u=np.zeros(5), y=np.zeros(4)), ValueError, "same number of samples"),
        (dict(u=np.zeros((5, 1, 1)), y=np.zeros(5)), ValueError, r"`u` must have shape"),
        (dict(u=np.zeros(5), y=["a"] * 5), TypeError, "`y` must be a numeric array"),
        (dict(u=np.zeros(0), y=np.zeros(0)), ValueError, "at least one sample"),
        (dict(Ts=-1.0), ValueError, "positive finite sampling time"),
        (dict(Ts="1"), TypeError, "`Ts` must be a positive number"),
        (dict(n=5), ValueError, r"0 < n <= T - 2 = 3"),
        (dict(n=4), ValueError, r"0 < n <= T - 2 = 3 .* got 4"),  # (one output scored)
        (dict(n=-1), ValueError, r"`n` must be 0 or satisfy"),
        (dict(n=1.5), TypeError, "`n` must be an integer"),  # (1.0 is the count 1)
        (dict(name=3), TypeError, "`name` must be a string"),
    ],
)
def test_record_bad_input(kwargs, error, pattern):
    args = dict(u=np.zeros(5), y=np.zeros(5), Ts=1.0, n=0, name="")
    args.update(kwargs)
    with pytest.raises(error, match=pattern):
        ds.Record(**args)


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(y=np.r_[np.ones(4), np.nan]), r"`y` must be finite .* at sample 4"),
        (dict(u=np.r_[np.inf, np.ones(4)]), r"`u` must be finite .* at sample 0"),
        (dict(y=np.c_[np.ones(5), np.r_[1.0, np.nan, 1, 1, 1]]), "`y` must be finite"),
    ],
)
def test_record_refuses_non_finite_samples(kwargs, pattern):
    """A Record of NaN outputs was accepted (the loaders refuse them in the files)."""
    args = dict(u=np.zeros(5), y=np.zeros(5), Ts=1.0) | kwargs
    with pytest.raises(ValueError, match=pattern):
        ds.Record(**args)


def test_record_round_trip_through_nonlinear_benchmarks():
    nb = pytest.importorskip("nonlinear_benchmarks")
    rng = np.random.default_rng(0)
    rec = ds.Record(
        u=rng.standard_normal(30), y=rng.standard_normal((30, 2)), Ts=0.01, n=7, name="x"
    )
    io = rec.to_nonlinear_benchmarks()
    assert isinstance(io, nb.Input_output_data)
    assert io.state_initialization_window_length == 7 and io.sampling_time == 0.01
    back = ds.Record.from_nonlinear_benchmarks(io)
    np.testing.assert_array_equal(back.u, rec.u)
    np.testing.assert_array_equal(back.y, rec.y)
    assert (back.Ts, back.n, back.name) == (0.01, 7, "x")
    # A training record (n = 0) goes out as None and comes back as 0; overrides apply.
    train = ds.Record.from_nonlinear_benchmarks(
        nb.Input_output_data(u=np.zeros(4), y=np.ones(4)), name="t"
    )
    assert (train.n, train.Ts, train.name) == (0, None, "t")
    assert ds.Record.from_nonlinear_benchmarks(io, n=3).n == 3
    # The package's error metrics accept the converted record.
    yhat = rec.y + 0.1
    theirs = nb.error_metrics.RMSE(io, yhat)
    np.testing.assert_allclose(rec.score(yhat).rmse, theirs, rtol=1e-13)


def test_record_from_something_else():
    with pytest.raises(TypeError, match="Input_output_data .* without u, y"):
        ds.Record.from_nonlinear_benchmarks(np.zeros(3))
