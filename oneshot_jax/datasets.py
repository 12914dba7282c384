"""Loaders for two public system-identification benchmarks (nonlinearbenchmark.org).

Nothing is downloaded, ever: the loaders read the benchmarks' own files from a folder
that you point them to. Where they look, in order:

1. the `path` argument (the benchmark's folder, its parent, or for the tanks the CSV
   file itself);
2. the environment variable `ONESHOT_JAX_DATA` (a folder holding `emps/` and
   `cascaded_tanks/`, or the files themselves);
3. `shared/data` next to the repository (`<repository>/../shared/data`), then
   `../shared/data` relative to the current working directory, when they exist.

If the files are not found, a `DatasetNotFoundError` (a `FileNotFoundError`) lists the
places searched and where to download the official files. A file that is there but not
what was expected (a missing variable or column, wrong lengths, non-numeric values)
raises a `DatasetFormatError` (a `ValueError`) naming the file and what was expected.

Benchmarks
----------

`load_emps` — Electro-Mechanical Positioning System (EMPS): a prismatic joint driven by a
DC motor, measured in closed loop under a PD controller at 1 kHz. Files `DATA_EMPS.mat`
(estimation) and `DATA_EMPS_PULSES.mat` (validation, with force pulses).
Cite: A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS",
Workshop on Nonlinear System Identification Benchmarks, 2019.

`load_cascaded_tanks` — two cascaded water tanks with overflow, 1024 samples per record
at Ts = 4 s. File `dataBenchmark.csv`.
Cite: M. Schoukens, P. Mattsson, T. Wigren, J.-P. Noël, "Cascaded tanks benchmark
combining soft and hard nonlinearities", Workshop on Nonlinear System Identification
Benchmarks, 2016.
"""

from __future__ import annotations

import csv
import dataclasses
import os
from pathlib import Path

import numpy as np

__all__ = [
    "ENV_VAR",
    "EMPS_IDIM_LS_REFERENCE",
    "EMPS",
    "EMPSRecord",
    "CascadedTanks",
    "DatasetNotFoundError",
    "DatasetFormatError",
    "load_emps",
    "load_cascaded_tanks",
    "default_data_dirs",
]

ENV_VAR = "ONESHOT_JAX_DATA"

_EMPS_URL = "https://www.nonlinearbenchmark.org/benchmarks/emps"
_TANKS_URL = "https://www.nonlinearbenchmark.org/benchmarks/cascaded-tanks"

EMPS_IDIM_LS_REFERENCE = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
"""IDIM-LS reference parameters printed in the EMPS description (Section 3.4):
M (kg), Fv (N/(m/s)), Fc (N), offset (N)."""

_EMPS_FILES = {"estimation": "DATA_EMPS.mat", "validation": "DATA_EMPS_PULSES.mat"}
_EMPS_SERIES = ("t", "qm", "qg", "vir")
_EMPS_SCALARS = ("kp", "kv", "gtau")
_TANKS_FILE = "dataBenchmark.csv"
_TANKS_COLUMNS = ("uEst", "uVal", "yEst", "yVal", "Ts")


class DatasetNotFoundError(FileNotFoundError):
    """The benchmark's files were not found in any of the searched places."""


class DatasetFormatError(ValueError):
    """A benchmark file exists but does not hold what the loader expects."""


# --------------------------------------------------------------------------- records


@dataclasses.dataclass(frozen=True)
class EMPSRecord:
    """One EMPS experiment (all arrays 1-D float64 of the same length n).

    **Fields:**

    - `t`: time, s.
    - `qm`: measured motor position (load side), m.
    - `qg`: reference position of the controller, m.
    - `vir`: controller output (motor force command), V; the force is `gtau * vir`, N.
    - `pulses`: the force-pulse signal of the validation experiment as stored in the
        file (`pulses_N`), zeros for the estimation record. In the file the pulses are
        already contained in `vir` (vir = controller output + pulse, see the experiment).
    - `file`: the file it was read from.
    """

    t: np.ndarray
    qm: np.ndarray
    qg: np.ndarray
    vir: np.ndarray
    pulses: np.ndarray
    file: Path

    def __len__(self):
        return self.t.shape[0]


@dataclasses.dataclass(frozen=True)
class EMPS:
    """The EMPS benchmark: estimation and validation records and the controller constants.

    **Fields:**

    - `estimation`: `EMPSRecord` from `DATA_EMPS.mat` (24,841 samples).
    - `validation`: `EMPSRecord` from `DATA_EMPS_PULSES.mat` (24,841 samples).
    - `kp`: position-loop gain, 1/s (160.18).
    - `kv`: velocity-loop gain, V/(m/s) (243.45).
    - `gtau`: drive gain, N/V (35.15).
    - `Ts`: sampling time, s (0.001, from the median spacing of `t`).

    Controller (benchmark description, eq. 6-7): nu = kp kv (qg - q) - kv q', tau =
    gtau nu, with q' the difference (q[k] - q[k-2]) / (2 Ts) and |nu| <= 10 V.
    """

    estimation: EMPSRecord
    validation: EMPSRecord
    kp: float
    kv: float
    gtau: float
    Ts: float


@dataclasses.dataclass(frozen=True)
class CascadedTanks:
    """The cascaded-tanks benchmark (1-D float64 arrays of 1024 samples each).

    **Fields:**

    - `u_est`, `u_val`: pump voltage, V (zero-order hold), estimation / validation.
    - `y_est`, `y_val`: water-level sensor of the lower tank, V (saturates at 10 V).
    - `Ts`: sampling time, s (4.0).
    - `file`: the CSV it was read from.

    Both records start from the same unknown initial state (benchmark description, Sec. 3).
    The figure of merit is the RMS of the simulation error on the validation record.
    """

    u_est: np.ndarray
    y_est: np.ndarray
    u_val: np.ndarray
    y_val: np.ndarray
    Ts: float
    file: Path

    @property
    def t(self) -> np.ndarray:
        """Sample times, s."""
        return self.Ts * np.arange(self.u_est.shape[0])


# --------------------------------------------------------------------------- locating


def default_data_dirs() -> list[Path]:
    """Data roots searched when no `path` is given, in order: `$ONESHOT_JAX_DATA` when set,
    then the `shared/data` folders beside the repository and beside the working directory
    that exist."""
    out = []
    env = os.environ.get(ENV_VAR)
    if env:
        out.append(Path(env).expanduser())
    for p in (
        Path(__file__).resolve().parents[2] / "shared" / "data",
        Path.cwd().resolve().parent / "shared" / "data",
    ):
        if p.is_dir() and all(p.resolve() != q.resolve() for q in out):
            out.append(p)
    return out


def _candidates(path, subdir):
    """Folders to look in: the given path (and its `subdir`), else the defaults."""
    roots = [Path(path).expanduser()] if path is not None else default_data_dirs()
    out = []
    for r in roots:
        out.extend([r / subdir, r])
    return out


def _not_found(what, files, searched, url, subdir):
    if searched:
        where = "Searched:\n" + "\n".join(f"  - {p}" for p in searched)
    else:
        where = f"No folder to search: no path given, ${ENV_VAR} unset and no ../shared/data."
    return DatasetNotFoundError(
        f"{what}: could not find {', '.join(files)}. {where}\n"
        f"Download the official files from {url} (nothing is downloaded automatically), "
        f"unpack them and pass path=<folder holding them>, or set ${ENV_VAR} to a folder "
        f"that holds them directly or in a subfolder '{subdir}/'."
    )


# --------------------------------------------------------------------------- EMPS


def _read_mat(file: Path, required_series, required_scalars, optional=()):
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
            f"variables {', '.join(required_series + required_scalars)}."
        ) from err
    names = [k for k in raw if not k.startswith("__")]
    missing = [k for k in (*required_series, *required_scalars) if k not in raw]
    if missing:
        raise DatasetFormatError(
            f"{file}: missing variable(s) {', '.join(missing)}; expected "
            f"{', '.join(required_series)} (column vectors of equal length) and "
            f"{', '.join(required_scalars)} (scalars); found {', '.join(names) or 'none'}."
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
        if a.ndim > 2 or (a.ndim == 2 and min(a.shape) != 1) or a.size < 2:
            raise DatasetFormatError(
                f"{file}: variable '{k}' must be a vector (n x 1), got shape {a.shape}."
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
        if not (isinstance(a, np.ndarray) and np.issubdtype(a.dtype, np.number)) or a.size != 1:
            raise DatasetFormatError(
                f"{file}: variable '{k}' must be a numeric scalar, got "
                f"{getattr(a, 'shape', type(a).__name__)}."
            )
        out[k] = float(np.asarray(a, dtype=np.float64).reshape(()))
        if not np.isfinite(out[k]):
            raise DatasetFormatError(f"{file}: variable '{k}' is not finite.")
    return out


def _emps_record(file: Path, with_pulses: bool):
    opt = ("pulses_N",) if with_pulses else ()
    d = _read_mat(file, _EMPS_SERIES, _EMPS_SCALARS, optional=opt)
    if with_pulses and "pulses_N" not in d:
        raise DatasetFormatError(
            f"{file}: missing variable pulses_N; the validation file is expected to hold "
            f"{', '.join(_EMPS_SERIES)}, pulses_N (vectors) and {', '.join(_EMPS_SCALARS)}."
        )
    if not np.all(np.diff(d["t"]) > 0):
        raise DatasetFormatError(f"{file}: variable 't' (time, s) must be strictly increasing.")
    pulses = d.get("pulses_N", np.zeros_like(d["t"]))
    rec = EMPSRecord(t=d["t"], qm=d["qm"], qg=d["qg"], vir=d["vir"], pulses=pulses, file=file)
    return rec, {k: d[k] for k in _EMPS_SCALARS}


def load_emps(path=None) -> EMPS:
    """Load the EMPS benchmark (estimation and validation records).

    **Arguments:**

    - `path`: a folder holding `DATA_EMPS.mat` and `DATA_EMPS_PULSES.mat`, or a folder
        with an `emps/` subfolder that holds them. Default: see the module docstring
        (`$ONESHOT_JAX_DATA`, then `../shared/data`).

    **Returns:**

    An `EMPS` with both records (t in s, qm and qg in m, vir in V), `kp` (1/s),
    `kv` (V/(m/s)), `gtau` (N/V) and the sampling time `Ts` (s).

    **Raises:**

    `DatasetNotFoundError` if the files are not found, `DatasetFormatError` if a file
    lacks a variable or has inconsistent shapes.
    """
    dirs = _candidates(path, "emps")
    if path is not None and Path(path).is_file():
        dirs = [Path(path).parent] + dirs
    found = None
    for d in dirs:
        if all((d / f).is_file() for f in _EMPS_FILES.values()):
            found = d
            break
    if found is None:
        partial = [d for d in dirs if any((d / f).is_file() for f in _EMPS_FILES.values())]
        if partial:
            d = partial[0]
            missing = [f for f in _EMPS_FILES.values() if not (d / f).is_file()]
            raise DatasetNotFoundError(
                f"EMPS benchmark: {d} holds only part of the data set, missing "
                f"{', '.join(missing)}. Download the official files from {_EMPS_URL}."
            )
        raise _not_found("EMPS benchmark", list(_EMPS_FILES.values()), dirs, _EMPS_URL, "emps")
    est, c_est = _emps_record(found / _EMPS_FILES["estimation"], with_pulses=False)
    val, c_val = _emps_record(found / _EMPS_FILES["validation"], with_pulses=True)
    for k in _EMPS_SCALARS:
        if not np.isclose(c_est[k], c_val[k], rtol=1e-9):
            raise DatasetFormatError(
                f"{found}: '{k}' differs between {_EMPS_FILES['estimation']} ({c_est[k]}) and "
                f"{_EMPS_FILES['validation']} ({c_val[k]}); expected the same controller."
            )
    Ts = float(np.median(np.diff(est.t)))
    return EMPS(
        estimation=est,
        validation=val,
        kp=c_est["kp"],
        kv=c_est["kv"],
        gtau=c_est["gtau"],
        Ts=round(Ts, 6),
    )


# --------------------------------------------------------------------------- tanks


def _read_tanks_csv(file: Path) -> CascadedTanks:
    expected = (
        f"a header row with columns {', '.join(_TANKS_COLUMNS)} and one numeric row "
        f"per sample (Ts in the first data row)"
    )
    try:
        with open(file, newline="") as fh:
            rows = [r for r in csv.reader(fh) if any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetFormatError(
            f"{file}: cannot be read as CSV ({err}); expected {expected}."
        ) from err
    if not rows:
        raise DatasetFormatError(f"{file}: empty file; expected {expected}.")
    header = [c.strip().strip('"') for c in rows[0]]
    missing = [c for c in _TANKS_COLUMNS if c not in header]
    if missing:
        raise DatasetFormatError(
            f"{file}: missing column(s) {', '.join(missing)} in the header {header}; "
            f"expected {expected}."
        )
    idx = {c: header.index(c) for c in _TANKS_COLUMNS}
    body = rows[1:]
    if len(body) < 2:
        raise DatasetFormatError(f"{file}: {len(body)} data row(s); expected {expected}.")
    cols = {c: [] for c in _TANKS_COLUMNS[:4]}
    for i, r in enumerate(body, start=2):
        for c in cols:
            try:
                cols[c].append(float(r[idx[c]]))
            except (IndexError, ValueError) as err:
                cell = r[idx[c]] if idx[c] < len(r) else "<missing>"
                raise DatasetFormatError(
                    f"{file}, line {i}: column '{c}' holds {cell!r}, not a number; "
                    f"expected {expected}."
                ) from err
    try:
        Ts = float(body[0][idx["Ts"]])
    except (IndexError, ValueError) as err:
        raise DatasetFormatError(
            f"{file}, line 2: column 'Ts' must hold the sampling time in s; expected {expected}."
        ) from err
    if not (np.isfinite(Ts) and Ts > 0):
        raise DatasetFormatError(f"{file}: Ts = {Ts} is not a positive sampling time (s).")
    arr = {c: np.asarray(v, dtype=np.float64) for c, v in cols.items()}
    for c, a in arr.items():
        if not np.all(np.isfinite(a)):
            raise DatasetFormatError(f"{file}: column '{c}' contains NaN or inf values.")
    return CascadedTanks(
        u_est=arr["uEst"], y_est=arr["yEst"], u_val=arr["uVal"], y_val=arr["yVal"], Ts=Ts, file=file
    )


def load_cascaded_tanks(path=None) -> CascadedTanks:
    """Load the cascaded-tanks benchmark.

    **Arguments:**

    - `path`: `dataBenchmark.csv` itself, a folder holding it, or a folder with a
        `cascaded_tanks/` subfolder that holds it. Default: see the module docstring.

    **Returns:**

    A `CascadedTanks` with the estimation and validation inputs (pump voltage, V) and
    outputs (lower-tank level sensor, V) and `Ts` = 4 s.

    **Raises:**

    `DatasetNotFoundError` if the file is not found, `DatasetFormatError` if it lacks a
    column or holds non-numeric values.
    """
    if path is not None and Path(path).expanduser().is_file():
        return _read_tanks_csv(Path(path).expanduser())
    dirs = _candidates(path, "cascaded_tanks")
    for d in dirs:
        if (d / _TANKS_FILE).is_file():
            return _read_tanks_csv(d / _TANKS_FILE)
    raise _not_found("Cascaded tanks benchmark", [_TANKS_FILE], dirs, _TANKS_URL, "cascaded_tanks")
