"""The Silverbox benchmark (an electronic Duffing oscillator)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ._files import (
    check_cache_dir,
    check_path,
    locate,
    not_found,
    read_csv,
    read_mat,
    require_length,
)
from ._record import Record, split_record

SILVERBOX_N_INIT = 50
"""The protocol's number of initial test outputs a model may use (all three test sets)."""

SILVERBOX_TS = 2**14 / 1e7
"""Sampling time, s: fs = 10^7 / 2^14 = 610.35 Hz (benchmark description;
`nonlinear_benchmarks` rounds it to 1 / 610.35 s)."""

_URL = "https://www.nonlinearbenchmark.org/benchmarks/silverbox"
_MAT = "SNLS80mV.mat"
_CSV = "SNLS80mV.csv"
_LENGTH = 131_072
# Official splits (0-based, end excluded), as in nonlinear_benchmarks.Silverbox.
_ARROW = (100, 40_575)
_ARROW_NO_EXTRAPOLATION = 32_000  # the first samples of the arrow test
_MULTISINE = (40_650, 127_400)
_TRAIN_FRACTION = 0.75


@dataclasses.dataclass(frozen=True)
class Silverbox:
    """The Silverbox benchmark with its official splits (u = V1, the input voltage, V;
    y = V2, the output voltage, V; Ts = 2^14 / 10^7 s, fs = 610.35 Hz).

    **Fields:**

    - `train`: the first 75 % of the multisine part `[40650:127400]` (65,062 samples),
        n = 0.
    - `test_multisine`: the last 25 % of the multisine part (21,688 samples), n = 50.
    - `test_arrow_full`: the arrow (filtered Gaussian noise of growing amplitude)
        `[100:40575]` (40,475 samples), n = 50; its end exceeds the training amplitudes.
    - `test_arrow_no_extrapolation`: the first 32,000 samples of `test_arrow_full`, n = 50.
    - `full`: the whole record `SNLS80mV` (131,072 samples), n = 0.
    - `file`: the file it was read from.

    `test` is `(test_multisine, test_arrow_full, test_arrow_no_extrapolation)`, the order
    of `nonlinear_benchmarks.Silverbox()`. The community reports the RMSE in mV.
    """

    train: Record
    test_multisine: Record
    test_arrow_full: Record
    test_arrow_no_extrapolation: Record
    full: Record
    file: Path

    @property
    def test(self) -> tuple[Record, Record, Record]:
        """The three test records, in the order of `nonlinear_benchmarks.Silverbox()`."""
        return (self.test_multisine, self.test_arrow_full, self.test_arrow_no_extrapolation)


def _read(file: Path) -> Silverbox:
    if file.suffix.lower() == ".mat":
        d = read_mat(file, ("V1", "V2"))
    else:
        d = read_csv(file, ("V1", "V2"))
    require_length(file, "the record V1, V2", d["V1"].shape[0], _MULTISINE[1], _LENGTH)
    full = Record(u=d["V1"], y=d["V2"], Ts=SILVERBOX_TS, n=0, name="Silverbox SNLS80mV")
    arrow = split_record(full, *_ARROW, n=SILVERBOX_N_INIT, name="test SB arrow full")
    no_extrapolation = split_record(
        arrow,
        0,
        _ARROW_NO_EXTRAPOLATION,
        n=SILVERBOX_N_INIT,
        name="test SB arrow no extrapolation",
    )
    multisine = split_record(full, *_MULTISINE)
    s = int(len(multisine) * _TRAIN_FRACTION)
    return Silverbox(
        train=split_record(multisine, 0, s, name="train SB multisine"),
        test_multisine=split_record(
            multisine, s, None, n=SILVERBOX_N_INIT, name="test SB multisine"
        ),
        test_arrow_full=arrow,
        test_arrow_no_extrapolation=no_extrapolation,
        full=full,
        file=file,
    )


def load_silverbox(path=None, *, download=False, cache_dir=None, base_url=None) -> Silverbox:
    """Load the Silverbox benchmark with the official train and test splits.

    **Arguments:**

    - `path`: `SNLS80mV.mat` or `SNLS80mV.csv` itself, a folder holding it (e.g. the
        unpacked `SilverboxFiles/`), or a folder with a `silverbox/` subfolder that holds
        it. Default: see the package docstring. The `.mat` file is preferred when both
        are there. The `.mat` file holds `V1` and `V2`; a `.csv` file has a header row
        naming the columns `V1` and `V2`, then one row per sample (the sampling time is
        the benchmark's constant, `SILVERBOX_TS`).
    - `download`: when the file is not found, fetch the official archive
        `SilverboxFiles.zip` into the cache folder (see `oneshot_jax.datasets`).
    - `cache_dir`: the cache folder (default `default_cache_dir()`).
    - `base_url`: fetch `<base_url>/SilverboxFiles.zip` instead of the official URL
        (default `$ONESHOT_JAX_DATA_URL`).

    **Returns:**

    A `Silverbox`: `train` (multisine, 75 %), the three test records (n = 50) and the full
    record, all as `Record`s with u = V1 and y = V2 in V.

    **Raises:**

    `DatasetNotFoundError` if the file is not found (or cannot be downloaded),
    `DatasetFormatError` if it lacks V1 or V2, holds non-numeric values, or is shorter
    than the official splits need (127,400 samples).

    **Reference:**

    T. Wigren, J. Schoukens, "Three free data sets for development and benchmarking in
    nonlinear system identification", European Control Conference (ECC), pp. 2933-2938,
    2013. Splits and protocol: Champneys et al., "Baseline results for selected nonlinear
    system identification benchmarks", arXiv:2405.10779, 2024, and `nonlinear_benchmarks`.
    """
    check_path(path)
    check_cache_dir(cache_dir)
    if path is not None and Path(path).expanduser().is_file():
        return _read(Path(path).expanduser())
    found, names = locate(
        path,
        ("silverbox", "silverbox/SilverboxFiles", "SilverboxFiles"),
        [(_MAT,), (_CSV,)],
        name="silverbox",
        download=download,
        cache_dir=cache_dir,
        base_url=base_url,
        on_missing=lambda dirs: not_found(
            "Silverbox benchmark", [_MAT, _CSV], dirs, _URL, "silverbox"
        ),
    )
    return _read(found / names[0])


__all__ = ["SILVERBOX_N_INIT", "SILVERBOX_TS", "Silverbox", "load_silverbox"]
