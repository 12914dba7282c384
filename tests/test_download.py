"""`download=True` against a local HTTP server on 127.0.0.1 serving synthetic archives.

Nothing here reaches the internet: every download goes to `base_url` (or
`$ONESHOT_JAX_DATA_URL`) pointing at the local server, and into a temporary cache folder.
"""

import dataclasses
import functools
import http.server
import threading
import zipfile

import numpy as np
import pytest
import scipy.io

from oneshot_jax import datasets as ds
from oneshot_jax.internal import DATASET_SOURCES, sha256


class _Handler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep the test output clean
        pass

    def do_GET(self):
        self.server.requests.append(self.path)
        if self.path.startswith("/truncated/"):
            body = b"PK" + b"\0" * 100
            self.send_response(200)
            self.send_header("Content-Length", str(10 * len(body)))
            self.end_headers()
            self.wfile.write(body)
            return
        if self.path.startswith("/half/"):  # no Content-Length, then the connection drops
            data = (self.server.www / self.path.removeprefix("/half/")).read_bytes()
            self.send_response(200)
            self.end_headers()
            self.wfile.write(data[: len(data) // 2])
            self.close_connection = True
            return
        super().do_GET()


@pytest.fixture
def server(tmp_path):
    """A server on 127.0.0.1 serving `tmp_path / "www"`; yields (base URL, folder, log)."""
    www = tmp_path / "www"
    www.mkdir()
    httpd = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(_Handler, directory=str(www))
    )
    httpd.requests = []
    httpd.www = www
    thread = threading.Thread(target=httpd.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", www, httpd.requests
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join()


def _emps_mats(folder, n=40):
    t = np.arange(n)[:, None] * 1e-3
    common = {"t": t, "qm": np.sin(t), "qg": np.sin(t), "vir": np.cos(t), "kp": 160.18,
              "kv": 243.45, "gtau": 35.15}  # fmt: skip
    scipy.io.savemat(folder / "DATA_EMPS.mat", common)
    scipy.io.savemat(folder / "DATA_EMPS_PULSES.mat", {**common, "pulses_N": np.zeros((n, 1))})
    return [folder / "DATA_EMPS.mat", folder / "DATA_EMPS_PULSES.mat"]


def _zip(archive, files, prefix=""):
    with zipfile.ZipFile(archive, "w") as zf:
        for f in files:
            zf.write(f, prefix + f.name)
    return archive


def _trust(monkeypatch, name, files):
    """Register the synthetic files' SHA-256 as the reference checksums."""
    src = DATASET_SOURCES[name]
    hashes = {f.name: sha256(f) for f in files}
    monkeypatch.setitem(DATASET_SOURCES, name, dataclasses.replace(src, files=hashes))


def _nothing_kept(cache, subdir):
    return not (cache / subdir).exists() and not list(cache.glob(f".{subdir}-*"))


def _served_emps(www, tmp_path, monkeypatch):
    """Synthetic EMPS files in `tmp_path / "src"`, served zipped and trusted: (files, the
    cache folder to download into)."""
    src = tmp_path / "src"
    src.mkdir()
    files = _emps_mats(src)
    _zip(www / "EMPS.zip", files)
    _trust(monkeypatch, "emps", files)
    return files, tmp_path / "cache"


def test_emps_download_checksum_and_cache(server, tmp_path, monkeypatch):
    base, www, log = server
    files, cache = _served_emps(www, tmp_path, monkeypatch)
    d = ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    assert log == ["/EMPS.zip"]
    assert d.estimation.file == cache / "emps" / "DATA_EMPS.mat"
    assert len(d.test) == 40 and d.test.n == 20
    for f in files:
        assert (cache / "emps" / f.name).read_bytes() == f.read_bytes()
    # Found in the cache next time: no second request, with or without download=True.
    ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    ds.load_emps(tmp_path / "empty", cache_dir=cache)
    assert log == ["/EMPS.zip"]
    # The cache is a default data root when it exists.
    monkeypatch.setenv(ds.CACHE_ENV_VAR, str(cache))
    assert ds.default_cache_dir() == cache and cache in ds.default_data_dirs()


def test_a_cached_file_that_changed_is_downloaded_again(server, tmp_path, monkeypatch):
    """download=True used to take whatever the cache held, checked once when downloaded."""
    base, www, log = server
    _, cache = _served_emps(www, tmp_path, monkeypatch)
    ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    cached = cache / "emps" / "DATA_EMPS_PULSES.mat"
    cached.write_bytes(cached.read_bytes() + b"edited")  # changed in the cache
    with pytest.raises(ds.DatasetFormatError, match="not a readable MATLAB"):
        ds.load_emps(tmp_path / "empty", cache_dir=cache)  # (not asked to download: as found)
    assert log == ["/EMPS.zip"]
    with pytest.warns(UserWarning, match=r"DATA_EMPS_PULSES\.mat in the download cache .* no "):
        ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    assert log == ["/EMPS.zip", "/EMPS.zip"]
    assert cached.read_bytes() == (tmp_path / "src" / "DATA_EMPS_PULSES.mat").read_bytes()
    # The user's own folder is theirs: its files are read as they are.
    own = tmp_path / "own"
    own.mkdir()
    _emps_mats(own, n=30)
    d = ds.load_emps(own, download=True, cache_dir=cache, base_url=base)
    assert len(d.test) == 30 and len(log) == 2


def test_checksum_mismatch_keeps_nothing(server, tmp_path):
    """Synthetic files are not the official ones: the reference SHA-256 refuses them."""
    base, www, _ = server
    src = tmp_path / "src"
    src.mkdir()
    _zip(www / "EMPS.zip", _emps_mats(src))
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetChecksumError, match=r"DATA_EMPS(_PULSES)?\.mat from .*SHA-256"):
        ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    assert _nothing_kept(cache, "emps")


def test_silverbox_download_warns_without_reference_checksum(server, tmp_path):
    """The archive's subfolder (SilverboxFiles/) is found in the cache; with no reference
    checksum the warning gives the file's SHA-256."""
    base, www, _ = server
    src = tmp_path / "src"
    src.mkdir()
    k = np.arange(131_072, dtype=float)
    scipy.io.savemat(src / "SNLS80mV.mat", {"V1": k[None], "V2": -k[None]})
    _zip(www / "SilverboxFiles.zip", [src / "SNLS80mV.mat"], prefix="SilverboxFiles/")
    cache = tmp_path / "cache"
    digest = sha256(src / "SNLS80mV.mat")
    with pytest.warns(UserWarning, match=f"no reference SHA-256.*{digest}"):
        d = ds.load_silverbox(tmp_path / "e", download=True, cache_dir=cache, base_url=base + "/")
    assert d.file == cache / "silverbox" / "SilverboxFiles" / "SNLS80mV.mat"
    assert d.train.u[0] == 40_650 and d.test_multisine.n == 50


def test_wiener_hammerstein_download_from_env_base_url(server, tmp_path, monkeypatch):
    """The WH archive is the .mat file itself; the base URL comes from the environment."""
    base, www, log = server
    k = np.arange(188_000, dtype=float)
    scipy.io.savemat(
        www / "WienerHammerBenchMark.mat",
        {"uBenchMark": k[:, None], "yBenchMark": k[:, None], "fs": np.array([[51200.0]])},
    )
    _trust(monkeypatch, "wiener_hammerstein", [www / "WienerHammerBenchMark.mat"])
    monkeypatch.setenv(ds.URL_ENV_VAR, base)
    monkeypatch.setenv(ds.CACHE_ENV_VAR, str(tmp_path / "cache"))
    d = ds.load_wiener_hammerstein(tmp_path / "empty", download=True)
    assert log == ["/WienerHammerBenchMark.mat"]
    assert d.file == tmp_path / "cache" / "wiener_hammerstein" / "WienerHammerBenchMark.mat"
    assert d.test.u[0] == 105_200


def test_http_error_says_where_to_get_the_files(server, tmp_path):
    base, _, _ = server
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetDownloadError) as e:
        ds.load_cascaded_tanks(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    msg = str(e.value)
    assert f"{base}/CascadedTanksFiles.zip" in msg and "404" in msg
    assert "nonlinearbenchmark.org/benchmarks/cascaded-tanks" in msg
    assert isinstance(e.value, ds.DatasetNotFoundError)
    assert _nothing_kept(cache, "cascaded_tanks")


def test_truncated_transfer_is_an_error(server, tmp_path):
    base, _, _ = server
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetDownloadError, match=r"truncated|IncompleteRead|incomplete"):
        ds.load_emps(tmp_path / "e", download=True, cache_dir=cache, base_url=base + "/truncated")
    assert _nothing_kept(cache, "emps")


def test_html_page_instead_of_an_archive(server, tmp_path):
    base, www, _ = server
    (www / "EMPS.zip").write_text("<!DOCTYPE html><html>Google Drive: virus scan</html>")
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetFormatError, match=r"did not return a zip archive .*DOCTYPE"):
        ds.load_emps(tmp_path / "e", download=True, cache_dir=cache, base_url=base)
    assert _nothing_kept(cache, "emps")


def test_a_zip_cut_short_is_not_blamed_on_the_link(server, tmp_path):
    """A zip without its end read "the download link may have changed"."""
    base, www, _ = server
    src = tmp_path / "src"
    src.mkdir()
    whole = _zip(tmp_path / "whole.zip", _emps_mats(src)).read_bytes()
    (www / "EMPS.zip").write_bytes(whole[: len(whole) // 2])
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetFormatError, match=r"incomplete: the download was cut short"):
        ds.load_emps(tmp_path / "e", download=True, cache_dir=cache, base_url=base)
    assert _nothing_kept(cache, "emps")


@pytest.mark.parametrize(
    "member, pattern",
    [("../escape.csv", "leaves the folder"), ("other.csv", "holds none of dataBenchmark")],
)
def test_bad_archives(server, tmp_path, member, pattern):
    base, www, _ = server
    with zipfile.ZipFile(www / "CascadedTanksFiles.zip", "w") as zf:
        zf.writestr(member, "uEst,uVal,yEst,yVal,Ts\n1,2,3,4,4\n1,2,3,4,\n")
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetFormatError, match=pattern):
        ds.load_cascaded_tanks(tmp_path / "e", download=True, cache_dir=cache, base_url=base)
    assert _nothing_kept(cache, "cascaded_tanks")
    assert not (tmp_path / "escape.csv").exists()


def test_a_truncated_file_without_checksum_is_not_kept(server, tmp_path, monkeypatch):
    """Half of the Wiener-Hammerstein .mat, sent without a length: with no reference
    checksum nothing could tell, and the cache kept the half file for good (every later
    call trusted it and failed to read it). It is read before it is kept."""
    base, www, _ = server
    k = np.arange(188_000, dtype=float)
    scipy.io.savemat(
        www / "WienerHammerBenchMark.mat",
        {"uBenchMark": k[:, None], "yBenchMark": -k[:, None], "fs": 51200.0},
    )
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetFormatError, match=r"truncated or damaged\. Nothing was kept"):
        ds.load_wiener_hammerstein(
            tmp_path / "e", download=True, cache_dir=cache, base_url=base + "/half"
        )
    assert _nothing_kept(cache, "wiener_hammerstein")
    # (the whole file, without a checksum, is kept with a warning)
    with pytest.warns(UserWarning, match="no reference SHA-256"):
        d = ds.load_wiener_hammerstein(
            tmp_path / "e", download=True, cache_dir=cache, base_url=base
        )
    assert d.test.u[0] == 105_200


def test_an_archive_member_failing_its_crc_is_a_format_error(server, tmp_path):
    base, www, _ = server
    archive = www / "CascadedTanksFiles.zip"
    csv = "uEst,uVal,yEst,yVal,Ts\n" + "".join(f"{i},{i},{i},{i},4\n" for i in range(40))
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("CascadedTanksFiles/dataBenchmark.csv", csv)
    data = bytearray(archive.read_bytes())
    at = data.index(b"uEst")
    data[at] ^= 1  # one bit of the member's data: its CRC-32 fails
    archive.write_bytes(bytes(data))
    cache = tmp_path / "cache"
    with pytest.raises(
        ds.DatasetFormatError, match=r"CascadedTanksFiles\.zip: the archive is corrupt"
    ):
        ds.load_cascaded_tanks(tmp_path / "e", download=True, cache_dir=cache, base_url=base)
    assert _nothing_kept(cache, "cascaded_tanks")


def test_an_incomplete_archive_keeps_nothing(server, tmp_path, monkeypatch):
    """An archive that holds DATA_EMPS.mat alone (with its checksum right) was refused
    after its file was installed: the cache kept DATA_EMPS.mat, against the promise that
    nothing is kept on failure. The set is checked before anything is installed."""
    base, www, _ = server
    src = tmp_path / "src"
    src.mkdir()
    files = _emps_mats(src)
    _zip(www / "EMPS.zip", files[:1])
    _trust(monkeypatch, "emps", files)
    cache = tmp_path / "cache"
    with pytest.raises(ds.DatasetFormatError, match=r"DATA_EMPS_PULSES\.mat.*Nothing was kept"):
        ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    assert _nothing_kept(cache, "emps")


@pytest.mark.parametrize("base_url", [5, b"http://127.0.0.1:1", "", "  "])
def test_a_base_url_that_is_not_a_url_is_refused(tmp_path, base_url):
    """An int or bytes failed deep in string handling, and "" fell back to the official
    internet addresses in silence."""
    with pytest.raises(TypeError, match=r"`base_url` must be a non-empty str"):
        ds.load_emps(tmp_path / "empty", download=True, cache_dir=tmp_path, base_url=base_url)


@pytest.mark.parametrize("download", ["no", 1, None])
def test_download_must_be_a_bool(server, tmp_path, download):
    """`download="no"` is truthy, and it downloaded."""
    base, _, log = server
    with pytest.raises(TypeError, match=r"`download` must be True or False"):
        ds.load_silverbox(tmp_path / "empty", download=download, cache_dir=tmp_path, base_url=base)
    assert log == []


def test_a_cache_folder_that_cannot_be_made_is_named(server, tmp_path):
    """A cache folder below a regular file failed with a bare NotADirectoryError."""
    base, _, log = server
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    with pytest.raises(ValueError, match=r"`cache_dir`: cannot use .*a_file.*download cache"):
        ds.load_emps(tmp_path / "empty", download=True, cache_dir=blocker / "cache", base_url=base)
    with pytest.raises(ValueError, match=r"`cache_dir`: .*a_file' is a file"):
        ds.load_emps(tmp_path / "empty", download=True, cache_dir=blocker, base_url=base)
    # without a download too (searched as a folder, it said only "not found")
    for load in (ds.load_emps, ds.load_cascaded_tanks, ds.load_silverbox):
        with pytest.raises(ValueError, match=r"`cache_dir`: .*a_file' is a file"):
            load(tmp_path / "empty", cache_dir=blocker)
    assert log == []


def test_a_download_in_a_subfolder_of_its_archive_is_found_again(server, tmp_path, monkeypatch):
    """An archive holding EMPS/DATA_EMPS.mat loaded once, then was downloaded again on
    every call (and not found without `download=True`): the lookup before a download
    searched <cache>/emps itself only."""
    base, www, log = server
    src = tmp_path / "src"
    src.mkdir()
    files = _emps_mats(src)
    _zip(www / "EMPS.zip", files, prefix="EMPS/")
    _trust(monkeypatch, "emps", files)
    cache = tmp_path / "cache"
    first = ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    assert first.estimation.file == cache / "emps" / "EMPS" / "DATA_EMPS.mat"
    again = ds.load_emps(tmp_path / "empty", download=True, cache_dir=cache, base_url=base)
    assert log == ["/EMPS.zip"]  # one download
    assert again.estimation.file == first.estimation.file
    found = ds.load_emps(tmp_path / "empty", cache_dir=cache)  # without download=True
    assert found.estimation.file == first.estimation.file
    # With no argument at all, the cache named by $ONESHOT_JAX_CACHE (a default root) is
    # searched in the archive's subfolders too (it was not: not found).
    monkeypatch.setenv(ds.HIDE_ENV_VAR, "1")
    monkeypatch.delenv(ds.ENV_VAR, raising=False)
    monkeypatch.setenv(ds.CACHE_ENV_VAR, str(cache))
    assert ds.load_emps().estimation.file == first.estimation.file
