"""The Wiener-Hammerstein benchmark (SYSID 2009)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ._files import (
    check_cache_dir,
    check_path,
    locate,
    not_found,
    positive_scalar,
    read_csv,
    read_mat,
    require_length,
)
from ._record import Record, split_record

WH_N_INIT = 50
"""The protocol's number of initial test outputs a model may use."""

_URL = "https://www.nonlinearbenchmark.org/benchmarks/wiener-hammerstein"
_MAT = "WienerHammerBenchMark.mat"
_CSV = "WienerHammerBenchmark.csv"  # sic: the CSV of the archive spells "Benchmark"
_LENGTH = 188_000
# Official splits (0-based, end excluded), as in nonlinear_benchmarks.WienerHammerBenchMark.
_USED = (5_200, 184_000)
_TRAIN = 100_000


@dataclasses.dataclass(frozen=True)
class WienerHammerstein:
    """The Wiener-Hammerstein benchmark with its official split (u = uBenchMark, the input
    voltage, V; y = yBenchMark, the output voltage, V; Ts = 1/fs with fs = 51.2 kHz).

    **Fields:**

    - `train`: samples `[5200:105200]` of the record (100,000 samples), n = 0.
    - `test`: samples `[105200:184000]` (78,800 samples), n = 50.
    - `full`: the whole record (188,000 samples), n = 0.
    - `file`: the file it was read from.

    The community reports the RMSE in mV.
    """

    train: Record
    test: Record
    full: Record
    file: Path


def _read(file: Path) -> WienerHammerstein:
    if file.suffix.lower() == ".mat":
        d = read_mat(file, ("uBenchMark", "yBenchMark"), ("fs",))
    else:
        d = read_csv(
            file, ("uBenchMark", "yBenchMark"), ("fs",), scalar_meaning="the sampling rate in Hz"
        )
    fs = positive_scalar(file, "fs", d["fs"], "sampling rate (Hz)")
    require_length(
        file, "the record uBenchMark, yBenchMark", d["uBenchMark"].shape[0], _USED[1], _LENGTH
    )
    full = Record(u=d["uBenchMark"], y=d["yBenchMark"], Ts=1.0 / fs, n=0, name="WH benchmark full")
    start, stop = _USED
    return WienerHammerstein(
        train=split_record(full, start, start + _TRAIN, name="train WH"),
        test=split_record(full, start + _TRAIN, stop, n=WH_N_INIT, name="test WH"),
        full=full,
        file=file,
    )


def load_wiener_hammerstein(path=None, *, download=False, cache_dir=None, base_url=None):
    """Load the Wiener-Hammerstein benchmark with the official train and test split.

    **Arguments:**

    - `path`: `WienerHammerBenchMark.mat` or `WienerHammerBenchmark.csv` itself, a folder
        holding it, or a folder with a `wiener_hammerstein/` subfolder that holds it.
        Default: see the package docstring. The `.mat` file is preferred when both are
        there. The `.mat` file holds `uBenchMark`, `yBenchMark` and `fs`; a `.csv` file
        has a header row naming the columns `uBenchMark`, `yBenchMark` and `fs`, then one
        row per sample (`fs`, in Hz, in the first data row; its other cells may be
        empty).
    - `download`: when the file is not found, fetch the official
        `WienerHammerBenchMark.mat` into the cache folder (see `oneshot_jax.datasets`).
    - `cache_dir`: the cache folder (default `default_cache_dir()`).
    - `base_url`: fetch `<base_url>/WienerHammerBenchMark.mat` instead of the official URL
        (default `$ONESHOT_JAX_DATA_URL`).

    **Returns:**

    A `WienerHammerstein`: `train` (100,000 samples), `test` (78,800 samples, n = 50) and
    the full record, as `Record`s with u = uBenchMark and y = yBenchMark in V.

    **Raises:**

    `DatasetNotFoundError` if the file is not found (or cannot be downloaded),
    `DatasetFormatError` if it lacks a variable, holds non-numeric values, or is shorter
    than the official split needs (184,000 samples).

    **Reference:**

    J. Schoukens, J. Suykens, L. Ljung, "Wiener-Hammerstein benchmark", 15th IFAC
    Symposium on System Identification (SYSID), Saint-Malo, 2009. Split and protocol:
    Champneys et al., "Baseline results for selected nonlinear system identification
    benchmarks", arXiv:2405.10779, 2024, and `nonlinear_benchmarks`.
    """
    check_path(path)
    check_cache_dir(cache_dir)
    if path is not None and Path(path).expanduser().is_file():
        return _read(Path(path).expanduser())
    found, names = locate(
        path,
        (
            "wiener_hammerstein",
            "wiener_hammerstein/WienerHammerstein2009Files",
            "WienerHammerstein2009Files",
        ),
        [(_MAT,), (_CSV,)],
        name="wiener_hammerstein",
        download=download,
        cache_dir=cache_dir,
        base_url=base_url,
        on_missing=lambda dirs: not_found(
            "Wiener-Hammerstein benchmark", [_MAT, _CSV], dirs, _URL, "wiener_hammerstein"
        ),
    )
    return _read(found / names[0])


__all__ = ["WH_N_INIT", "WienerHammerstein", "load_wiener_hammerstein"]
