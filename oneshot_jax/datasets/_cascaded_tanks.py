"""The cascaded-tanks benchmark (two water tanks with overflow)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

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
from ._record import Record

TANKS_N_INIT = 5
"""The protocol's number of initial test outputs a model may use (Champneys et al. 2024;
`nonlinear_benchmarks` 1.0.1 sets 50)."""

_URL = "https://www.nonlinearbenchmark.org/benchmarks/cascaded-tanks"
_CSV = "dataBenchmark.csv"
_MAT = "dataBenchmark.mat"
_SERIES = ("uEst", "uVal", "yEst", "yVal")


@dataclasses.dataclass(frozen=True)
class CascadedTanks:
    """The cascaded-tanks benchmark (1-D float64 arrays of 1024 samples each).

    **Fields:**

    - `u_est`, `u_val`: pump voltage, V (zero-order hold), estimation / validation.
    - `y_est`, `y_val`: water-level sensor of the lower tank, V (saturates at 10 V).
    - `Ts`: sampling time, s (4.0).
    - `file`: the file it was read from.

    Both records start from the same unknown initial state (benchmark description, Sec. 3).
    The figure of merit is the RMS of the simulation error on the validation record.

    **Protocol views** (`train`, `test`): u = `u_est`/`u_val`, y = `y_est`/`y_val`; a
    model may use the test input and the first 5 test outputs (Champneys et al. 2024).
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

    @property
    def train(self) -> Record:
        """`Record` of the estimation experiment (uEst, yEst), n = 0."""
        return Record(u=self.u_est, y=self.y_est, Ts=self.Ts, n=0, name="train Cascaded_Tanks")

    @property
    def test(self) -> Record:
        """`Record` of the validation experiment (uVal, yVal), n = 5."""
        return Record(
            u=self.u_val, y=self.y_val, Ts=self.Ts, n=TANKS_N_INIT, name="test Cascaded_Tanks"
        )


def _read(file: Path) -> CascadedTanks:
    if file.suffix.lower() == ".mat":
        d = read_mat(file, _SERIES, ("Ts",))
    else:
        d = read_csv(file, _SERIES, ("Ts",), scalar_meaning="the sampling time in s")
    Ts = positive_scalar(file, "Ts", d["Ts"], "sampling time (s)")
    # The test view keeps TANKS_N_INIT outputs for the initial state and scores at least
    # two more (`Record`, `benchmark_scores`).
    require_length(
        file, "the record uEst, uVal, yEst, yVal", d["uEst"].shape[0], TANKS_N_INIT + 2, 1024
    )
    return CascadedTanks(
        u_est=d["uEst"], y_est=d["yEst"], u_val=d["uVal"], y_val=d["yVal"], Ts=Ts, file=file
    )


def load_cascaded_tanks(path=None, *, download=False, cache_dir=None, base_url=None):
    """Load the cascaded-tanks benchmark.

    **Arguments:**

    - `path`: `dataBenchmark.csv` (or `.mat`) itself, a folder holding it, or a folder with
        a `cascaded_tanks/` subfolder that holds it. Default: see the package docstring.
        The `.csv` file is read when a folder holds both; a file given as `path` is read
        whatever its name.
    - `download`: when the file is not found, fetch the official archive into the cache
        folder and verify the files' SHA-256 (see `oneshot_jax.datasets`).
    - `cache_dir`: the cache folder (default `default_cache_dir()`).
    - `base_url`: fetch `<base_url>/CascadedTanksFiles.zip` instead of the official URLs
        (default `$ONESHOT_JAX_DATA_URL`).

    **Returns:**

    A `CascadedTanks` with the estimation and validation inputs (pump voltage, V) and
    outputs (lower-tank level sensor, V) and `Ts` = 4 s; `.train` and `.test` are the
    protocol's `Record`s (n = 5 on the test record, as Champneys et al. 2024 give it;
    the `nonlinear_benchmarks` package 1.0.1 sets 50, so its scores are taken from sample
    50 on and are not comparable digit for digit: `benchmark_scores(z, zhat, 50)` gives
    them).

    **Raises:**

    `DatasetNotFoundError` if the file is not found (or cannot be downloaded),
    `DatasetFormatError` if it lacks a column, holds non-numeric values, or holds fewer
    than `TANKS_N_INIT + 2` samples (the test view's initial window and the two scored
    samples the protocol needs at least).

    **Reference:**

    M. Schoukens, P. Mattsson, T. Wigren, J.-P. Noël, "Cascaded tanks benchmark combining
    soft and hard nonlinearities", Workshop on Nonlinear System Identification Benchmarks,
    2016. Protocol: Champneys et al., "Baseline results for selected nonlinear system
    identification benchmarks", arXiv:2405.10779, 2024.
    """
    check_path(path)
    check_cache_dir(cache_dir)
    if path is not None and Path(path).expanduser().is_file():
        return _read(Path(path).expanduser())
    found, names = locate(
        path,
        ("cascaded_tanks", "cascaded_tanks/CascadedTanksFiles", "CascadedTanksFiles"),
        [(_CSV,), (_MAT,)],
        name="cascaded_tanks",
        download=download,
        cache_dir=cache_dir,
        base_url=base_url,
        on_missing=lambda dirs: not_found(
            "Cascaded tanks benchmark", [_CSV, _MAT], dirs, _URL, "cascaded_tanks"
        ),
    )
    return _read(found / names[0])


__all__ = ["CascadedTanks", "TANKS_N_INIT", "load_cascaded_tanks"]
