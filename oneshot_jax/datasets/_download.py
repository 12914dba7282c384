"""`download=True`: fetch a benchmark's official files into the cache folder, verify their
SHA-256 checksums, and unpack them. Standard library only (urllib, hashlib, zipfile).

Each benchmark has a `Source`: the official URLs of its archive (tried in order), the
archive's file name, and the data files the loader reads with their SHA-256 where a
reference copy was at hand. With a base URL (the `base_url` argument or
`$ONESHOT_JAX_DATA_URL`), the archive is fetched from `<base_url>/<archive name>` instead:
a mirror, or a local server in tests.
"""

from __future__ import annotations

import dataclasses
import hashlib
import http.client
import os
import shutil
import tempfile
import urllib.request
import zipfile
import zlib
from pathlib import Path

from .._caller_warnings import warn
from ._locations import (
    CACHE_ENV_VAR,
    DatasetFormatError,
    DatasetNotFoundError,
    default_cache_dir,
)

URL_ENV_VAR = "ONESHOT_JAX_DATA_URL"
"""Environment variable naming a base URL that replaces the official download URLs."""

_TIMEOUT_S = 60.0


class DatasetDownloadError(DatasetNotFoundError):
    """The files could not be downloaded (network error, HTTP error, truncated transfer)."""


class DatasetChecksumError(DatasetFormatError):
    """A downloaded file's SHA-256 differs from the reference checksum."""


def _gdrive(file_id):
    # Google Drive's direct-download form for files below its virus-scan size limit.
    return f"https://drive.usercontent.google.com/download?id={file_id}&export=download&confirm=t"


@dataclasses.dataclass(frozen=True)
class Source:
    """Where a benchmark's official files come from.

    **Fields:**

    - `subdir`: the benchmark's folder in the cache (and in a data folder).
    - `archive`: the file name of what is downloaded (a `.zip`, or the data file itself).
    - `urls`: official URLs of the archive, tried in order.
    - `files`: file name -> SHA-256 (hex) of the data files the loader reads, or None
        where no reference checksum is known. Any one of the files suffices (e.g. the
        `.mat` or the `.csv` version); every one found is verified.
    - `page`: the benchmark's web page, named in error messages.
    """

    subdir: str
    archive: str
    urls: tuple[str, ...]
    files: dict
    page: str


SOURCES = {
    "emps": Source(
        subdir="emps",
        archive="EMPS.zip",
        urls=(_gdrive("1zwoXYa9-3f8NQ0ohzmjpF7UxbNgRTHkS"),),
        files={
            "DATA_EMPS.mat": "6cf6814ae14618795da0101aae2bb97ff0c6351b0501b5492751b02b07facf7e",
            "DATA_EMPS_PULSES.mat": (
                "0eab75bb1f6b16228ee78791343a88bf9bfd9a51036ac9807d7b5fc11c0e1704"
            ),
        },
        page="https://www.nonlinearbenchmark.org/benchmarks/emps",
    ),
    "cascaded_tanks": Source(
        subdir="cascaded_tanks",
        archive="CascadedTanksFiles.zip",
        urls=(
            "https://data.4tu.nl/file/d4810b78-6cdd-48fe-8950-9bd601e5f47f/"
            "3b697e42-01a4-4979-a370-813a456c36f5",
            _gdrive("1HnQf_gu0g_UlggoBqy2s34l9YJiFdN01"),
        ),
        files={
            "dataBenchmark.csv": "ef2388ed822f3aef4aa80d6b0f2b466dd80b361786b3eafc7a2957c31ea323a7",
            "dataBenchmark.mat": None,
        },
        page="https://www.nonlinearbenchmark.org/benchmarks/cascaded-tanks",
    ),
    "silverbox": Source(
        subdir="silverbox",
        archive="SilverboxFiles.zip",
        urls=(_gdrive("17iS-6oBUUgrmiAcrZoG9S5sOaljZnDSy"),),
        files={"SNLS80mV.mat": None, "SNLS80mV.csv": None},
        page="https://www.nonlinearbenchmark.org/benchmarks/silverbox",
    ),
    "wiener_hammerstein": Source(
        subdir="wiener_hammerstein",
        archive="WienerHammerBenchMark.mat",
        urls=(
            "http://www.ee.kth.se/~hjalmars/ifac_tc11_benchmarks/2009_wienerhammerstein/"
            "WienerHammerBenchMark.mat",
        ),
        files={"WienerHammerBenchMark.mat": None, "WienerHammerBenchmark.csv": None},
        page="https://www.nonlinearbenchmark.org/benchmarks/wiener-hammerstein",
    ),
}


def sha256(file) -> str:
    """SHA-256 of a file, hex."""
    h = hashlib.sha256()
    with open(file, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _get(url, dest: Path):
    """Stream `url` into `dest`; a truncated transfer is an error."""
    req = urllib.request.Request(url, headers={"User-Agent": "oneshot_jax"})
    with urllib.request.urlopen(req, timeout=_TIMEOUT_S) as resp, open(dest, "wb") as fh:
        expected = resp.headers.get("Content-Length")
        size = 0
        for block in iter(lambda: resp.read(1 << 20), b""):
            fh.write(block)
            size += len(block)
    if expected is not None and size != int(expected):
        raise OSError(f"transfer truncated: {size} of {expected} bytes")


def _unzip(archive: Path, into: Path, url):
    if not zipfile.is_zipfile(archive):
        with open(archive, "rb") as fh:
            head = fh.read(64)
        damaged = head.startswith(b"PK")  # a zip's start, without its end: cut short
        raise DatasetFormatError(
            f"{url} did not return a zip archive ({archive.stat().st_size} bytes starting "
            f"with {head[:40]!r}); "
            + (
                "it starts as one but is incomplete: the download was cut short or damaged. "
                "Nothing was kept."
                if damaged
                else "the download link may have changed."
            )
        )
    with zipfile.ZipFile(archive) as zf:
        for m in zf.namelist():
            p = Path(m)
            if p.is_absolute() or ".." in p.parts:
                raise DatasetFormatError(f"{url}: archive member {m!r} leaves the folder.")
        try:
            zf.extractall(into)
        except (zipfile.BadZipFile, EOFError, OSError, zlib.error) as err:
            raise DatasetFormatError(
                f"{url}: the archive is corrupt ({type(err).__name__}: {err}); the download "
                f"was damaged. Nothing was kept."
            ) from err


def _install(src: Path, dest: Path):
    """Move `src` to `dest` file by file with `os.replace` (atomic), merging into a folder
    that a concurrent call may have installed meanwhile instead of deleting it."""
    if src.is_dir():
        if dest.exists() and not dest.is_dir():
            dest.unlink()
        dest.mkdir(parents=True, exist_ok=True)
        for p in src.iterdir():
            _install(p, dest / p.name)
    else:
        if dest.is_dir():
            shutil.rmtree(dest, ignore_errors=True)
        os.replace(src, dest)


def fetch(name, *, cache_dir=None, base_url=None, alternatives=None) -> Path:
    """Download a benchmark's official files into the cache and verify them.

    **Arguments:**

    - `name`: `"emps"`, `"cascaded_tanks"`, `"silverbox"` or `"wiener_hammerstein"`.
    - `cache_dir`: the cache folder; default `default_cache_dir()`. The files land in
        `<cache_dir>/<name>/`, unpacked as in the official archive.
    - `base_url`: fetch `<base_url>/<archive name>` instead of the official URLs; default
        `$ONESHOT_JAX_DATA_URL` when set.
    - `alternatives`: tuples of file names, each a complete set (the loader's): the
        download must hold one of them in one folder, or nothing is installed.

    **Returns:**

    The cache subfolder `<cache_dir>/<name>`.

    **Raises:**

    `DatasetDownloadError` (a `DatasetNotFoundError`) when no URL answers;
    `DatasetChecksumError` (a `DatasetFormatError`) when a file's SHA-256 differs from the
    reference, and `DatasetFormatError` when the archive is not a zip or lacks the data
    files. Nothing is left in the cache on failure. A `UserWarning` gives the SHA-256 of
    each data file that has no reference checksum.
    """
    if name not in SOURCES:
        raise ValueError(f"`name` must be one of {', '.join(SOURCES)}, got {name!r}.")
    src = SOURCES[name]
    if base_url is not None and (not isinstance(base_url, str) or not base_url.strip()):
        raise TypeError(
            f"`base_url` must be a non-empty str (a URL such as 'https://host/folder') or "
            f"None, got {base_url!r}."
        )
    base_url = base_url if base_url is not None else os.environ.get(URL_ENV_VAR)
    urls = [f"{base_url.rstrip('/')}/{src.archive}"] if base_url else list(src.urls)
    root = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    target = root / src.subdir
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # a regular file on the way, no permission, a read-only disk
        raise ValueError(
            f"`cache_dir`: cannot use {str(root)!r} as the download cache folder "
            f"({type(err).__name__}: {err.strerror or err}); pass cache_dir=<a folder you can "
            f"write> or set ${CACHE_ENV_VAR}."
        ) from err
    if not root.is_dir():
        raise ValueError(f"`cache_dir`: {str(root)!r} is not a folder.")
    try:
        scratch = tempfile.TemporaryDirectory(prefix=f".{src.subdir}-", dir=root)
    except OSError as err:  # a folder that exists but cannot be written (read-only)
        raise ValueError(
            f"`cache_dir`: cannot write into {str(root)!r} ({type(err).__name__}: "
            f"{err.strerror or err}); pass cache_dir=<a folder you can write> or set "
            f"${CACHE_ENV_VAR}."
        ) from err
    with scratch as tmp:
        tmp = Path(tmp)
        archive = tmp / src.archive
        errors = []
        for url in urls:
            try:
                _get(url, archive)
                break
            except (OSError, http.client.HTTPException, ValueError) as err:
                errors.append(f"  - {url}: {err}")
        else:
            raise DatasetDownloadError(
                f"could not download {src.archive}:\n" + "\n".join(errors) + "\n"
                f"Download the official files by hand from {src.page} and pass "
                f"path=<folder holding them>."
            )
        unpacked = tmp / "unpacked"
        unpacked.mkdir()
        if src.archive.endswith(".zip"):
            _unzip(archive, unpacked, url)
        else:
            shutil.move(archive, unpacked / src.archive)
        found = {f: sorted(unpacked.rglob(f)) for f in src.files}
        if not any(found.values()):
            raise DatasetFormatError(
                f"{url}: the download holds none of {', '.join(src.files)}; expected the "
                f"official files of {src.page}."
            )
        for f, paths in found.items():
            for p in paths:
                got = sha256(p)
                if src.files[f] is None and p.suffix.lower() == ".mat":
                    import scipy.io

                    try:  # no checksum: at least refuse a truncated or damaged file
                        scipy.io.loadmat(p)
                    except Exception as err:  # noqa: BLE001
                        raise DatasetFormatError(
                            f"{f} from {url}: not a readable MATLAB file ({type(err).__name__}: "
                            f"{err}); the download is truncated or damaged. Nothing was kept. "
                            f"Download it by hand from {src.page}."
                        ) from err
                if src.files[f] is None:
                    warn(
                        f"{f} from {url}: no reference SHA-256 is known for this file, so it "
                        f"is not verified; its SHA-256 is {got}.",
                        UserWarning,
                        stacklevel=2,
                    )
                elif got != src.files[f]:
                    raise DatasetChecksumError(
                        f"{f} from {url}: SHA-256 {got} differs from the official file's "
                        f"{src.files[f]}; the download is corrupt or not the official "
                        f"file. Nothing was kept. Download it by hand from {src.page}."
                    )
        if alternatives is not None:  # a complete set, or nothing is kept
            folders = {p.parent for p in unpacked.rglob("*") if p.is_file()}
            if not any(
                all((d / f).is_file() for f in names) for d in folders for names in alternatives
            ):
                raise DatasetFormatError(
                    f"{url}: the download does not hold "
                    f"{' or '.join(map(' and '.join, alternatives))} in one folder. Nothing "
                    f"was kept. Download the files by hand from {src.page}."
                )
        target.mkdir(parents=True, exist_ok=True)
        for p in unpacked.iterdir():
            _install(p, target / p.name)
    return target
