"""The EMPS benchmark (Electro-Mechanical Positioning System)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ._files import check_cache_dir, check_path, locate, not_found, require_length
from ._files import read_mat as _read_mat
from ._locations import DatasetFormatError, DatasetNotFoundError
from ._record import Record

EMPS_IDIM_LS_REFERENCE = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
"""IDIM-LS reference parameters printed in the EMPS description (Section 3.4):
M (kg), Fv (N/(m/s)), Fc (N), offset (N)."""

EMPS_N_INIT = 20
"""The protocol's number of initial test outputs a model may use (Champneys et al. 2024)."""

_URL = "https://www.nonlinearbenchmark.org/benchmarks/emps"
_FILES = {"estimation": "DATA_EMPS.mat", "validation": "DATA_EMPS_PULSES.mat"}
_SERIES = ("t", "qm", "qg", "vir")
_SCALARS = ("kp", "kv", "gtau")


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
    - `Ts`: sampling time, s (0.001: the span of `t` over its number of intervals, to 10
        significant digits).

    Controller (benchmark description, eq. 6-7): nu = kp kv (qg - q) - kv q', tau =
    gtau nu, with q' the difference (q[k] - q[k-2]) / (2 Ts) and |nu| <= 10 V.

    **Protocol views** (`train`, `test`): the community scores EMPS in open loop, with the
    force command `vir` (V) as input and the position `qm` (m) as output; a model may use
    the test input and the first 20 test outputs. Positions are in m here; the community
    reports the RMSE in mm (multiply by 1000).
    """

    estimation: EMPSRecord
    validation: EMPSRecord
    kp: float
    kv: float
    gtau: float
    Ts: float

    @property
    def train(self) -> Record:
        """`Record` of the estimation experiment: u = `vir` (V), y = `qm` (m), n = 0."""
        r = self.estimation
        return Record(u=r.vir, y=r.qm, Ts=self.Ts, n=0, name="train (DATA_EMPS)")

    @property
    def test(self) -> Record:
        """`Record` of the validation experiment: u = `vir` (V), y = `qm` (m), n = 20."""
        r = self.validation
        return Record(u=r.vir, y=r.qm, Ts=self.Ts, n=EMPS_N_INIT, name="test (DATA_EMPS_PULSES)")


def _record(file: Path, with_pulses: bool):
    opt = ("pulses_N",) if with_pulses else ()
    d = _read_mat(file, _SERIES, _SCALARS, optional=opt)
    if with_pulses and "pulses_N" not in d:
        raise DatasetFormatError(
            f"{file}: missing variable pulses_N; the validation file is expected to hold "
            f"{', '.join(_SERIES)}, pulses_N (vectors) and {', '.join(_SCALARS)}."
        )
    if with_pulses:  # the test view keeps EMPS_N_INIT outputs and scores at least two more
        require_length(file, "the record t, qm, qg, vir", d["t"].shape[0], EMPS_N_INIT + 2, 24841)
    dt = np.diff(d["t"])
    if not np.all(dt > 0):
        raise DatasetFormatError(f"{file}: variable 't' (time, s) must be strictly increasing.")
    # The models step at one sampling time: a gap in t would be simulated as one sample.
    k = int(np.argmax(np.abs(dt - np.median(dt))))
    if abs(dt[k] - np.median(dt)) > 0.01 * np.median(dt):
        raise DatasetFormatError(
            f"{file}: variable 't' (time, s) is not uniformly sampled: t[{k + 1}] - t[{k}] = "
            f"{dt[k]:.6g} s against a median spacing of {np.median(dt):.6g} s; the EMPS "
            f"models expect one sampling time."
        )
    pulses = d.get("pulses_N", np.zeros_like(d["t"]))
    rec = EMPSRecord(t=d["t"], qm=d["qm"], qg=d["qg"], vir=d["vir"], pulses=pulses, file=file)
    return rec, {k: d[k] for k in _SCALARS}


def _missing(dirs):
    # Half a data set gets its own message: the other file was probably not unpacked.
    for d in dirs:
        if any((d / f).is_file() for f in _FILES.values()):
            missing = [f for f in _FILES.values() if not (d / f).is_file()]
            return DatasetNotFoundError(
                f"EMPS benchmark: {d} holds only part of the data set, missing "
                f"{', '.join(missing)}. Download the official files from {_URL}."
            )
    return not_found("EMPS benchmark", [" and ".join(_FILES.values())], dirs, _URL, "emps")


def _sampling_time(record):
    """The mean spacing of a record's `t` (s; uniform to 1 %: `_record`), its span over its
    number of intervals, to 10 significant digits: 1 ms exactly for the official files,
    whose single spacings carry round-off of 2e-5 relative (their median is 0.99998 ms)."""
    t = np.asarray(record.t, np.float64)
    return float(f"{(t[-1] - t[0]) / (t.size - 1):.10g}")


def load_emps(path=None, *, download=False, cache_dir=None, base_url=None) -> EMPS:
    """Load the EMPS benchmark (estimation and validation records).

    **Arguments:**

    - `path`: a folder holding `DATA_EMPS.mat` and `DATA_EMPS_PULSES.mat` (or one of
        them, whose folder is searched for both by these names), or a folder with an
        `emps/` subfolder that holds them. Default: see the package docstring
        (`$ONESHOT_JAX_DATA`, then `../shared/data`, then the cache).
    - `download`: when the files are not found, fetch the official archive into the
        cache folder and verify the files' SHA-256 (see `oneshot_jax.datasets`).
    - `cache_dir`: the cache folder (default `default_cache_dir()`).
    - `base_url`: fetch `<base_url>/EMPS.zip` instead of the official URL (default
        `$ONESHOT_JAX_DATA_URL`).

    **Returns:**

    An `EMPS` with both records (t in s, qm and qg in m, vir in V), `kp` (1/s),
    `kv` (V/(m/s)), `gtau` (N/V) and the sampling time `Ts` (s); `.train` and `.test`
    are the protocol's `Record`s (u = vir, y = qm, n = 20 on the test record).

    **Raises:**

    `DatasetNotFoundError` if the files are not found (or cannot be downloaded),
    `DatasetFormatError` if a file lacks a variable or has inconsistent shapes, or the
    validation record holds fewer than `EMPS_N_INIT + 2` samples (the test view's initial
    window and the two scored samples the protocol needs at least).

    **Reference:**

    A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS", Workshop on
    Nonlinear System Identification Benchmarks, 2019. Protocol: Champneys et al.,
    "Baseline results for selected nonlinear system identification benchmarks",
    arXiv:2405.10779, 2024.
    """
    check_path(path)
    check_cache_dir(cache_dir)
    found, _ = locate(
        path,
        ("emps",),
        [tuple(_FILES.values())],
        name="emps",
        download=download,
        cache_dir=cache_dir,
        base_url=base_url,
        on_missing=_missing,
    )
    est, c_est = _record(found / _FILES["estimation"], with_pulses=False)
    val, c_val = _record(found / _FILES["validation"], with_pulses=True)
    for k in _SCALARS:
        if not np.isclose(c_est[k], c_val[k], rtol=1e-9):
            raise DatasetFormatError(
                f"{found}: '{k}' differs between {_FILES['estimation']} ({c_est[k]}) and "
                f"{_FILES['validation']} ({c_val[k]}); expected the same controller."
            )
    Ts, Ts_val = (_sampling_time(r) for r in (est, val))
    if not np.isclose(Ts_val, Ts, rtol=1e-3):
        raise DatasetFormatError(
            f"{val.file}: sampled every {Ts_val:.6g} s but {_FILES['estimation']} every "
            f"{Ts:.6g} s; expected both records at one sampling time (1 ms)."
        )
    return EMPS(
        estimation=est,
        validation=val,
        kp=c_est["kp"],
        kv=c_est["kv"],
        gtau=c_est["gtau"],
        Ts=Ts,
    )


__all__ = ["EMPS", "EMPSRecord", "EMPS_IDIM_LS_REFERENCE", "EMPS_N_INIT", "load_emps"]
