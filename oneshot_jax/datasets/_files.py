"""Shared parts of the loaders: finding a benchmark's files (downloading them when asked)
and readers for the benchmarks' MATLAB and CSV files with errors that name the file and
what was expected. Where the files are looked for, and the error types, are in
`_locations.py`."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from .._caller_warnings import warn
from .._checks import check_path as check_path
from ._download import SOURCES, fetch, sha256
from ._locations import (
    CACHE_ENV_VAR,
    ENV_VAR,
    HIDE_ENV_VAR,
    DatasetFormatError,
    DatasetNotFoundError,
    candidates,
    data_hidden,
    default_cache_dir,
    find_folder,
)


def check_cache_dir(cache_dir):
    """`cache_dir` checked as `check_path` checks a path, and refused where it names a
    file: searched as a folder, it gave "not found" without saying why."""
    check_path(cache_dir, "cache_dir", "a folder")
    if cache_dir is not None and Path(cache_dir).expanduser().is_file():
        raise ValueError(
            f"`cache_dir`: {str(cache_dir)!r} is a file; give the folder of the download "
            "cache (the data files' own path goes to `path`)."
        )


def _folders(target: Path) -> list[Path]:
    """The folders under a download's `target` that hold files, shallowest first (the
    archive may keep the files in a subfolder, e.g. SilverboxFiles/)."""
    if not target.is_dir():
        return []
    found = {p.parent for p in target.rglob("*") if p.is_file()}
    return sorted(found, key=lambda p: (len(p.parts), str(p)))


def locate(path, subdirs, alternatives, *, name, download, cache_dir, base_url, on_missing):
    """Find a benchmark's files, downloading them when asked.

    **Arguments:**

    - `path`: the user's folder (or file, whose folder is used), or None for the defaults.
    - `subdirs`: subfolders of a root that may hold the files (e.g. `silverbox`).
    - `alternatives`: tuples of file names, each a complete set, in order of preference.
    - `name`: the benchmark's key in `_download.SOURCES`.
    - `download`, `cache_dir`, `base_url`: see `_download.fetch`; the cache folder is
        searched too when `cache_dir` is given or `download` is True.
    - `on_missing`: called with the searched folders; returns the exception to raise.

    **Returns:**

    `(folder, files)`: the folder and the set of file names found there.
    """
    if not isinstance(download, (bool, np.bool_)):  # ("no" is truthy: it would download)
        raise TypeError(f"`download` must be True or False, got {download!r}.")
    given_file = None  # (a file of another name than the benchmark's: named if not found)
    if path is not None and Path(path).expanduser().is_file():
        given_file = Path(path).expanduser()
        path = given_file.parent
    env = os.environ.get(ENV_VAR)
    if path is None and env and not Path(env).expanduser().is_dir():
        raise DatasetNotFoundError(
            f"${ENV_VAR}={env!r} is not a folder; set it to the folder that holds the "
            f"benchmark files (or their subfolders such as '{subdirs[0]}/'), or unset it."
        )
    dirs = candidates(path, subdirs)
    caches = []  # (download caches searched: what an earlier download unpacked, in
    # whatever subfolders its archive keeps, is looked for in each)
    if cache_dir is not None or download:
        cache = cache_dir if cache_dir is not None else default_cache_dir()
        dirs += candidates(cache, subdirs)
        caches.append(Path(cache).expanduser())
    if path is None and default_cache_dir().resolve() in {d.resolve() for d in dirs}:
        caches.append(default_cache_dir())  # (a root of the defaults)
    for folder in caches:
        dirs += _folders(folder / SOURCES[name].subdir)
    dirs = list(dict.fromkeys(dirs))
    folder, names = find_folder(dirs, alternatives)
    if folder is not None and download:
        changed = _changed_in_cache(folder, names, name, cache)
        if changed:
            warn(
                f"{', '.join(changed)} in the download cache {folder} no longer "
                f"match{'es' if len(changed) == 1 else ''} the official file's SHA-256 "
                "(damaged or edited since it was downloaded): downloading the files again.",
                UserWarning,
                stacklevel=3,
            )
            folder = None
    if folder is not None:
        return folder, names
    if not download:
        err = on_missing(dirs)
        if path is not None and not Path(path).expanduser().exists():
            err = DatasetNotFoundError(f"path={str(path)!r} does not exist. {err}")
        elif given_file is not None and all(given_file.name not in a for a in alternatives):
            err = DatasetNotFoundError(
                f"path={str(given_file)!r} is a file the loader does not read: it reads "
                f"{' or '.join(map(' and '.join, alternatives))} by these names, from the "
                f"folder of a file given as `path` (give the files these names). {err}"
            )
        raise err
    target = fetch(name, cache_dir=cache_dir, base_url=base_url, alternatives=alternatives)
    folder, names = find_folder(_folders(target), alternatives)
    if folder is None:
        raise DatasetFormatError(
            f"{target}: the download does not hold {' or '.join(map(' and '.join, alternatives))}."
        )
    return folder, names


def _changed_in_cache(folder, names, name, cache):
    """The files of `names` in `folder` that an earlier download put in the cache (under
    `<cache>/<subdir>`) and whose SHA-256 differs from their reference checksum (files
    without one, and the user's own folders, are not judged)."""
    src = SOURCES[name]
    try:
        folder.resolve().relative_to((Path(cache).expanduser() / src.subdir).resolve())
    except ValueError:
        return []
    return [f for f in sorted(names) if src.files.get(f) and sha256(folder / f) != src.files[f]]


def not_found(what, files, searched, url, subdir):
    """A `DatasetNotFoundError` listing the places searched and where to get the files."""
    if searched:
        where = "Searched:\n" + "\n".join(f"  - {p}" for p in searched)
    else:
        where = (
            f"No folder to search: no path given, ${ENV_VAR} unset, no ../shared/data and no "
            f"download cache."
        )
        if data_hidden():
            where += f" (${HIDE_ENV_VAR} is set: ../shared/data and the cache are hidden.)"
    return DatasetNotFoundError(
        f"{what}: could not find {' or '.join(files)}. {where}\n"
        f"Download the official files from {url} and pass path=<folder holding them>, or "
        f"set ${ENV_VAR} to a folder that holds them directly or in a subfolder "
        f"'{subdir}/', or call the loader with download=True to fetch them into "
        f"{default_cache_dir()} (${CACHE_ENV_VAR}); from a shell: python -c 'import "
        f"oneshot_jax as oj; oj.datasets.load_{subdir}(download=True)'."
    )


# --------------------------------------------------------------------------- readers


def read_mat(file: Path, required_series, required_scalars=(), optional=()) -> dict:
    """Read a MATLAB 5 `.mat` file: the `required_series` (and present `optional` ones) as
    1-D float64 vectors of one common length, the `required_scalars` as floats.

    **Raises:**

    `DatasetFormatError` naming the file and the variable when the file cannot be read, a
    variable is missing, is not numeric, is not a vector (or scalar), has a different
    length, or holds NaN or inf.
    """
    import scipy.io

    try:
        raw = scipy.io.loadmat(file, squeeze_me=False)
    except NotImplementedError as err:  # MATLAB v7.3 (HDF5) files
        raise DatasetFormatError(
            f"{file}: a MATLAB v7.3 (HDF5) file, which scipy.io cannot read; expected the "
            f"benchmark's original MATLAB 5 .mat file ({err})."
        ) from err
    except Exception as err:  # noqa: BLE001 - any parse failure is a format error
        raise DatasetFormatError(
            f"{file}: not a readable MATLAB .mat file ({type(err).__name__}: {err}); expected "
            f"variables {', '.join((*required_series, *required_scalars))}."
        ) from err
    names = [k for k in raw if not k.startswith("__")]
    missing = [k for k in (*required_series, *required_scalars) if k not in raw]
    if missing:
        scalars = f" and {', '.join(required_scalars)} (scalars)" if required_scalars else ""
        raise DatasetFormatError(
            f"{file}: missing variable(s) {', '.join(missing)}; expected "
            f"{', '.join(required_series)} (column vectors of equal length){scalars}; "
            f"found {', '.join(names) or 'none'}."
        )
    out = {}
    n = None
    for k in (*required_series, *[o for o in optional if o in raw]):
        a = raw[k]
        if not (isinstance(a, np.ndarray) and np.issubdtype(a.dtype, np.number)):
            raise DatasetFormatError(
                f"{file}: variable '{k}' must be numeric, got {type(a).__name__}"
                f" of dtype {getattr(a, 'dtype', None)}."
            )
        if np.iscomplexobj(a):
            raise DatasetFormatError(f"{file}: variable '{k}' must be real, got dtype {a.dtype}.")
        if a.ndim > 2 or (a.ndim == 2 and min(a.shape) != 1) or a.size < 2:
            raise DatasetFormatError(
                f"{file}: variable '{k}' must be a vector (n x 1 or 1 x n), got shape {a.shape}."
            )
        a = np.asarray(a, dtype=np.float64).reshape(-1)
        if n is None:
            n = a.shape[0]
        elif a.shape[0] != n:
            raise DatasetFormatError(
                f"{file}: variable '{k}' has {a.shape[0]} samples but '{required_series[0]}' "
                f"has {n}; expected vectors of equal length."
            )
        if not np.all(np.isfinite(a)):
            raise DatasetFormatError(f"{file}: variable '{k}' contains NaN or inf values.")
        out[k] = a
    for k in required_scalars:
        a = raw[k]
        if (
            not (isinstance(a, np.ndarray) and np.issubdtype(a.dtype, np.number))
            or np.iscomplexobj(a)
            or a.size != 1
        ):
            raise DatasetFormatError(
                f"{file}: variable '{k}' must be a numeric scalar, got "
                f"{getattr(a, 'shape', type(a).__name__)}."
            )
        out[k] = float(np.asarray(a, dtype=np.float64).reshape(()))
        if not np.isfinite(out[k]):
            raise DatasetFormatError(f"{file}: variable '{k}' is not finite.")
    return out


def read_csv(file: Path, series, scalars=(), scalar_meaning="") -> dict:
    """Read a benchmark CSV: a header row naming the columns, then one numeric row per
    sample. The `series` columns become 1-D float64 vectors; each of the `scalars` columns
    holds one number in the first data row (the others may be empty), returned as a float.

    **Arguments:**

    - `file`: the CSV file.
    - `series`: names of the per-sample columns.
    - `scalars`: names of the one-value columns (e.g. the sampling time `Ts`).
    - `scalar_meaning`: what the scalars are, for the error messages (e.g. "the sampling
        time in s").

    **Raises:**

    `DatasetFormatError` naming the file (and the line and column) when it cannot be read,
    is empty, lacks a column, or holds a non-numeric, NaN or inf value.
    """
    where = f" ({', '.join(scalars)} in the first data row)" if scalars else ""
    expected = (
        f"a header row with columns {', '.join((*series, *scalars))} and one numeric row "
        f"per sample{where}"
    )
    try:
        # utf-8-sig: spreadsheets export CSV with a byte-order mark before the first column.
        with open(file, newline="", encoding="utf-8-sig") as fh:
            rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DatasetFormatError(
            f"{file}: cannot be read as CSV ({err}); expected {expected}."
        ) from err
    if not rows:
        raise DatasetFormatError(f"{file}: empty file; expected {expected}.")
    header = [c.strip().strip('"') for c in rows[0]]
    twice = sorted({c for c in (*series, *scalars) if header.count(c) > 1})
    if twice:
        raise DatasetFormatError(
            f"{file}: column(s) {', '.join(twice)} appear more than once in the header "
            f"{header}; expected {expected}."
        )
    missing = [c for c in (*series, *scalars) if c not in header]
    if missing:
        raise DatasetFormatError(
            f"{file}: missing column(s) {', '.join(missing)} in the header {header}; "
            f"expected {expected}."
        )
    idx = {c: header.index(c) for c in (*series, *scalars)}
    body = rows[1:]
    if len(body) < 2:
        raise DatasetFormatError(f"{file}: {len(body)} data row(s); expected {expected}.")
    cols = {}
    try:  # fast path: NumPy parses whole columns
        for c in series:
            j = idx[c]
            cols[c] = np.array([r[j] if j < len(r) else "" for r in body], dtype=np.float64)
    except ValueError:  # find the first bad cell, row by row, for the message
        for i, r in enumerate(body):
            for c in series:
                cell = r[idx[c]] if idx[c] < len(r) else "<missing>"
                try:
                    float(cell)
                except ValueError as err:
                    raise DatasetFormatError(
                        f"{file}, line {i + 2}: column '{c}' holds {cell!r}, not a number; "
                        f"expected {expected}."
                    ) from err
        raise DatasetFormatError(f"{file}: non-numeric values; expected {expected}.") from None
    for c, a in cols.items():
        if not np.all(np.isfinite(a)):
            raise DatasetFormatError(f"{file}: column '{c}' contains NaN or inf values.")
    out = dict(cols)
    for c in scalars:
        try:
            out[c] = float(body[0][idx[c]])
        except (IndexError, ValueError) as err:
            raise DatasetFormatError(
                f"{file}, line 2: column '{c}' must hold {scalar_meaning or 'a number'}; "
                f"expected {expected}."
            ) from err
    return out


def positive_scalar(file, name, value, meaning):
    """`value` if it is a positive finite number, else a `DatasetFormatError`."""
    if not (np.isfinite(value) and value > 0):
        raise DatasetFormatError(f"{file}: {name} = {value} is not a positive {meaning}.")
    return value


def require_length(file, what, n, minimum, official):
    """A `DatasetFormatError` unless the record has at least `minimum` samples, and a
    `UserWarning` where its length is not the official file's (a file cut short, say,
    which still parses: its scores are not the benchmark's)."""
    if n < minimum:
        raise DatasetFormatError(
            f"{file}: {what} has {n} samples; the official splits need at least {minimum} "
            f"(the official file has {official})."
        )
    if n != official:
        warn(
            f"{file}: {what} has {n} samples, the official file {official}: not the "
            "official record (cut short or edited?), so scores on it are not the "
            "benchmark's.",
            UserWarning,
            stacklevel=4,
        )
