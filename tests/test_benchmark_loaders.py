"""Silverbox and Wiener-Hammerstein loaders on synthetic files in the official formats.

The splits use the official absolute sample indices, so the synthetic records have the
official lengths; their input is the sample index (u[k] = k), which makes every split
boundary visible. The official files are not needed; where `nonlinear_benchmarks` is
installed, its own loaders read the same synthetic files (placed where its cache looks, so
it downloads nothing) and must give the same records.
"""

import re

import numpy as np
import pytest
import scipy.io

from oneshot_jax import datasets as ds

SB_N, WH_N = 131_072, 188_000


def _sb_arrays(n=SB_N):
    k = np.arange(n, dtype=float)
    return k, np.sin(1e-3 * k)


def _wh_arrays(n=WH_N):
    k = np.arange(n, dtype=float)
    return k, np.cos(1e-3 * k)


def _write_csv(file, header, columns, first_row_scalars=()):
    """A CSV like the archives': a header, then one row per sample; scalar columns hold
    their value in the first data row only."""
    file.parent.mkdir(parents=True, exist_ok=True)
    body = np.column_stack(columns)
    lines = [",".join(header)]
    for i, row in enumerate(body):
        extra = [repr(v) for v in first_row_scalars] if i == 0 else [""] * len(first_row_scalars)
        lines.append(",".join([*(repr(float(v)) for v in row), *extra]))
    file.write_text("\n".join(lines) + "\n")
    return file


@pytest.fixture(scope="module")
def sb_mat(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sb") / "SilverboxFiles"
    folder.mkdir()
    u, y = _sb_arrays()
    scipy.io.savemat(folder / "SNLS80mV.mat", {"V1": u[None, :], "V2": y[None, :]})
    return folder / "SNLS80mV.mat"


@pytest.fixture(scope="module")
def wh_mat(tmp_path_factory):
    folder = tmp_path_factory.mktemp("wh")
    u, y = _wh_arrays()
    scipy.io.savemat(
        folder / "WienerHammerBenchMark.mat",
        {"uBenchMark": u[:, None], "yBenchMark": y[:, None], "fs": np.array([[51200.0]])},
    )
    return folder / "WienerHammerBenchMark.mat"


# ----------------------------------------------------------------------- Silverbox


def test_silverbox_official_splits(sb_mat):
    d = ds.load_silverbox(sb_mat)
    u, y = _sb_arrays()
    expected = {  # record: (first source index, length, n)
        "train": (40_650, 65_062, 0),
        "test_multisine": (40_650 + 65_062, 21_688, 50),
        "test_arrow_full": (100, 40_475, 50),
        "test_arrow_no_extrapolation": (100, 32_000, 50),
        "full": (0, SB_N, 0),
    }
    for field, (start, length, n) in expected.items():
        rec = getattr(d, field)
        assert isinstance(rec, ds.Record)
        assert (rec.u[0], len(rec), rec.n) == (start, length, n), field
        np.testing.assert_array_equal(rec.y, y[start : start + length])
        assert rec.Ts == pytest.approx(1 / 610.3515625, rel=1e-12) == ds.SILVERBOX_TS
    assert d.train.u[-1] + 1 == d.test_multisine.u[0]  # the 75/25 split is contiguous
    assert d.test_multisine.u[-1] == 127_399 and d.test_arrow_full.u[-1] == 40_574
    assert d.test == (d.test_multisine, d.test_arrow_full, d.test_arrow_no_extrapolation)
    assert [r.name for r in d.test] == [
        "test SB multisine",
        "test SB arrow full",
        "test SB arrow no extrapolation",
    ]
    assert d.file == sb_mat


def test_silverbox_csv_gives_the_same_records(sb_mat, tmp_path):
    u, y = _sb_arrays()
    csv = _write_csv(tmp_path / "silverbox" / "SNLS80mV.csv", ['"V1"', '"V2"'], [u, y])
    c, m = ds.load_silverbox(tmp_path), ds.load_silverbox(sb_mat)
    assert c.file == csv
    for a, b in zip((c.train, *c.test), (m.train, *m.test)):
        np.testing.assert_array_equal(a.u, b.u)
        np.testing.assert_array_equal(a.y, b.y)
    # With both files in one folder the .mat is preferred.
    (tmp_path / "silverbox" / "SNLS80mV.mat").write_bytes(sb_mat.read_bytes())
    assert ds.load_silverbox(tmp_path).file.name == "SNLS80mV.mat"


def test_silverbox_search_order(sb_mat, tmp_path, monkeypatch):
    # The unpacked archive folder, its parent, and a data root with silverbox/SilverboxFiles.
    assert ds.load_silverbox(sb_mat.parent).file == sb_mat
    assert ds.load_silverbox(sb_mat.parent.parent).file == sb_mat
    root = tmp_path / "root"
    (root / "silverbox" / "SilverboxFiles").mkdir(parents=True)
    target = root / "silverbox" / "SilverboxFiles" / "SNLS80mV.mat"
    target.write_bytes(sb_mat.read_bytes())
    monkeypatch.setenv(ds.ENV_VAR, str(root))
    assert ds.load_silverbox().file == target


def test_silverbox_matches_nonlinear_benchmarks(sb_mat, tmp_path):
    nb = pytest.importorskip("nonlinear_benchmarks")
    (tmp_path / "Silverbox" / "SilverboxFiles").mkdir(parents=True)
    (tmp_path / "Silverbox" / "SilverboxFiles.zip").write_bytes(b"")  # "already downloaded"
    (tmp_path / "Silverbox" / "SilverboxFiles" / "SNLS80mV.mat").write_bytes(sb_mat.read_bytes())
    train, tests = nb.Silverbox(dir_placement=tmp_path)
    d = ds.load_silverbox(sb_mat)
    for theirs, ours in zip((train, *tests), (d.train, *d.test)):
        np.testing.assert_array_equal(theirs.u, ours.u)
        np.testing.assert_array_equal(theirs.y, ours.y)
        assert (theirs.state_initialization_window_length or 0) == ours.n
        # The package rounds fs to 610.35 Hz.
        assert theirs.sampling_time == pytest.approx(ours.Ts, rel=1e-5)


# ----------------------------------------------------------------------- Wiener-Hammerstein


def test_wiener_hammerstein_official_split(wh_mat):
    d = ds.load_wiener_hammerstein(wh_mat)
    u, y = _wh_arrays()
    assert (d.train.u[0], len(d.train), d.train.n) == (5_200, 100_000, 0)
    assert (d.test.u[0], len(d.test), d.test.n) == (105_200, 78_800, 50)
    assert d.test.u[-1] == 183_999 and len(d.full) == WH_N
    np.testing.assert_array_equal(d.test.y, y[105_200:184_000])
    assert d.train.Ts == d.test.Ts == pytest.approx(1 / 51200, rel=1e-15)
    assert (d.train.name, d.test.name) == ("train WH", "test WH")


def test_wiener_hammerstein_csv(wh_mat, tmp_path):
    u, y = _wh_arrays()
    _write_csv(
        tmp_path / "wiener_hammerstein" / "WienerHammerBenchmark.csv",
        ["uBenchMark", "yBenchMark", "fs"],
        [u, y],
        first_row_scalars=(51200,),
    )
    c, m = ds.load_wiener_hammerstein(tmp_path), ds.load_wiener_hammerstein(wh_mat)
    assert c.file.name == "WienerHammerBenchmark.csv"
    np.testing.assert_array_equal(c.test.u, m.test.u)
    np.testing.assert_array_equal(c.train.y, m.train.y)
    assert c.test.Ts == m.test.Ts


def test_wiener_hammerstein_matches_nonlinear_benchmarks(wh_mat, tmp_path):
    nb = pytest.importorskip("nonlinear_benchmarks")
    folder = tmp_path / "WienerHammerBenchMark"
    folder.mkdir()
    (folder / "WienerHammerBenchMark.mat").write_bytes(wh_mat.read_bytes())
    train, test = nb.WienerHammerBenchMark(dir_placement=tmp_path)
    d = ds.load_wiener_hammerstein(wh_mat)
    for theirs, ours in ((train, d.train), (test, d.test)):
        np.testing.assert_array_equal(theirs.u, ours.u)
        np.testing.assert_array_equal(theirs.y, ours.y)
        assert (theirs.state_initialization_window_length or 0) == ours.n
        assert theirs.sampling_time == ours.Ts


# ----------------------------------------------------------------------- bad input


def test_missing_files_say_where_to_get_them(tmp_path):
    for load, names, url in (
        (ds.load_silverbox, r"SNLS80mV\.mat or SNLS80mV\.csv", "silverbox"),
        (
            ds.load_wiener_hammerstein,
            r"WienerHammerBenchMark\.mat or WienerHammerBenchmark\.csv",
            "wiener-hammerstein",
        ),
    ):
        with pytest.raises(ds.DatasetNotFoundError) as e:
            load(tmp_path)
        msg = str(e.value)
        assert re.search(names, msg), msg
        assert f"nonlinearbenchmark.org/benchmarks/{url}" in msg
        assert str(tmp_path) in msg and ds.ENV_VAR in msg and "download=True" in msg


def test_short_records_are_refused(tmp_path):
    u, y = _sb_arrays(127_399)
    scipy.io.savemat(tmp_path / "SNLS80mV.mat", {"V1": u[None], "V2": y[None]})
    with pytest.raises(ds.DatasetFormatError, match=r"SNLS80mV\.mat.*127399 samples.*127400"):
        ds.load_silverbox(tmp_path)
    u, y = _wh_arrays(1000)
    scipy.io.savemat(
        tmp_path / "WienerHammerBenchMark.mat",
        {"uBenchMark": u[:, None], "yBenchMark": y[:, None], "fs": np.array([[51200.0]])},
    )
    with pytest.raises(ds.DatasetFormatError, match=r"1000 samples.*at least 184000"):
        ds.load_wiener_hammerstein(tmp_path)


@pytest.mark.parametrize(
    "content, pattern",
    [
        ({"V1": np.zeros((1, 10))}, r"missing variable\(s\) V2"),
        ({"V1": np.zeros((1, 10)), "V2": np.zeros((1, 9))}, r"'V2' has 9 samples"),
        ({"V1": np.zeros((2, 10)), "V2": np.zeros((1, 10))}, r"'V1' must be a vector"),
        ({"V1": np.full((1, 10), np.nan), "V2": np.zeros((1, 10))}, r"'V1' contains NaN"),
    ],
)
def test_silverbox_malformed_mat(tmp_path, content, pattern):
    scipy.io.savemat(tmp_path / "SNLS80mV.mat", content)
    with pytest.raises(ds.DatasetFormatError, match=pattern) as e:
        ds.load_silverbox(tmp_path)
    assert "SNLS80mV.mat" in str(e.value)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ("V1,V3\n1,2\n3,4\n", r"missing column\(s\) V2"),
        ("V1,V2\n1,2\n3,oops\n", r"line 3: column 'V2' holds 'oops'"),
        ("V1,V2\n1,2\n3\n", r"line 3: column 'V2' holds '<missing>'"),
        ("V1,V2\n1,2\n", r"1 data row"),
    ],
)
def test_silverbox_malformed_csv(tmp_path, text, pattern):
    f = tmp_path / "SNLS80mV.csv"
    f.write_text(text)
    with pytest.raises(ds.DatasetFormatError, match=pattern) as e:
        ds.load_silverbox(f)
    assert "SNLS80mV.csv" in str(e.value)


@pytest.mark.parametrize(
    "fs, pattern",
    [
        ("", r"column 'fs' must hold the sampling rate in Hz"),
        ("-5", r"fs = -5.0 is not a positive sampling rate"),
    ],
)
def test_wiener_hammerstein_bad_sampling_rate(tmp_path, fs, pattern):
    f = tmp_path / "WienerHammerBenchmark.csv"
    f.write_text(f"uBenchMark,yBenchMark,fs\n1,2,{fs}\n3,4,\n")
    with pytest.raises(ds.DatasetFormatError, match=pattern):
        ds.load_wiener_hammerstein(f)
    scipy.io.savemat(
        tmp_path / "WienerHammerBenchMark.mat",
        {"uBenchMark": np.zeros((5, 1)), "yBenchMark": np.zeros((5, 1))},
    )
    with pytest.raises(ds.DatasetFormatError, match=r"missing variable\(s\) fs"):
        ds.load_wiener_hammerstein(tmp_path / "WienerHammerBenchMark.mat")
