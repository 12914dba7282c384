"""Loaders for four public system-identification benchmarks (nonlinearbenchmark.org), with
the official splits and the community's protocol.

Where the loaders look
----------------------

The loaders read the benchmarks' own files from, in order:

1. the `path` argument (the file itself, the benchmark's folder, or its parent);
2. the environment variable `ONESHOT_JAX_DATA` (a folder holding `emps/`,
   `cascaded_tanks/`, `silverbox/`, `wiener_hammerstein/`, or the files themselves; set
   to anything but a folder, it is an error, not skipped);
3. `shared/data` next to the repository (`<repository>/../shared/data`), then
   `../shared/data` relative to the current working directory, when they exist;
4. the download cache (`default_cache_dir()`: `$ONESHOT_JAX_CACHE`, else the user cache
   folder such as `~/.cache/oneshot_jax`), when it exists.

Setting `ONESHOT_JAX_HIDE_DATA=1` hides the places of 3. and 4. that no variable names
(the `shared/data` folders and the user cache folder), as on a fresh checkout without the
data: the tests that need the benchmark files then skip, naming the files.

If the files are not found, a `DatasetNotFoundError` (a `FileNotFoundError`) lists the
places searched and where to download the official files. A file that is there but not
what was expected (a missing variable or column, wrong lengths, non-numeric values)
raises a `DatasetFormatError` (a `ValueError`) naming the file and what was expected.

Downloading
-----------

Nothing is downloaded unless asked. With `download=True`, a loader that finds no files
fetches the official archive (the URLs of `nonlinear_benchmarks`) into the cache folder
(`cache_dir` argument, default `default_cache_dir()`), unpacks it, and checks the data
files' SHA-256 against reference checksums (known for EMPS and the tanks' CSV; for the
other files a `UserWarning` gives the checksum of what was downloaded). Files that an
earlier download left in the cache are checked again by the next loader call with
`download=True`: one that no longer matches its reference checksum (damaged or edited
since) is downloaded again, with a warning. A base URL
(`base_url` argument, or `$ONESHOT_JAX_DATA_URL`) replaces the official URLs: the archive
is then fetched from `<base_url>/<archive name>`.

The protocol
------------

Every loader gives `train` and `test` views as `Record`s (u, y, Ts, n, name). A model may
use the test input and only the first `n` test outputs (EMPS 20, Cascaded Tanks 5,
Silverbox 50, Wiener-Hammerstein 50); it is scored by RMSE(y[n:], yhat[n:]), with NRMSE,
R² and FIT (`record.score(yhat)`, `oneshot_jax.metrics.benchmark_scores`). `Record`
converts to and from `nonlinear_benchmarks.Input_output_data`.

Reference: M. D. Champneys, G. I. Beintema, R. Tóth, M. Schoukens, T. J. Rogers, "Baseline
results for selected nonlinear system identification benchmarks", arXiv:2405.10779, 2024.

Benchmarks
----------

`load_emps` — Electro-Mechanical Positioning System (EMPS): a prismatic joint driven by a
DC motor, measured in closed loop under a PD controller at 1 kHz. Files `DATA_EMPS.mat`
(estimation) and `DATA_EMPS_PULSES.mat` (validation, with force pulses).
Cite: A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS",
Workshop on Nonlinear System Identification Benchmarks, 2019.

`load_cascaded_tanks` — two cascaded water tanks with overflow, 1024 samples per record
at Ts = 4 s. File `dataBenchmark.csv` (or `dataBenchmark.mat`).
Cite: M. Schoukens, P. Mattsson, T. Wigren, J.-P. Noël, "Cascaded tanks benchmark
combining soft and hard nonlinearities", Workshop on Nonlinear System Identification
Benchmarks, 2016.

`load_silverbox` — an electronic Duffing oscillator (Silverbox), 131,072 samples at
610.35 Hz. File `SNLS80mV.mat` (or `SNLS80mV.csv`).
Cite: T. Wigren, J. Schoukens, "Three free data sets for development and benchmarking in
nonlinear system identification", European Control Conference, 2013.

`load_wiener_hammerstein` — an electronic Wiener-Hammerstein system, 188,000 samples at
51.2 kHz. File `WienerHammerBenchMark.mat` (or `WienerHammerBenchmark.csv`).
Cite: J. Schoukens, J. Suykens, L. Ljung, "Wiener-Hammerstein benchmark", 15th IFAC
Symposium on System Identification, 2009.
"""

from ._cascaded_tanks import TANKS_N_INIT as TANKS_N_INIT
from ._cascaded_tanks import CascadedTanks as CascadedTanks
from ._cascaded_tanks import load_cascaded_tanks as load_cascaded_tanks
from ._download import URL_ENV_VAR as URL_ENV_VAR
from ._download import DatasetChecksumError as DatasetChecksumError
from ._download import DatasetDownloadError as DatasetDownloadError
from ._emps import EMPS as EMPS
from ._emps import EMPS_IDIM_LS_REFERENCE as EMPS_IDIM_LS_REFERENCE
from ._emps import EMPS_N_INIT as EMPS_N_INIT
from ._emps import EMPSRecord as EMPSRecord
from ._emps import load_emps as load_emps
from ._locations import CACHE_ENV_VAR as CACHE_ENV_VAR
from ._locations import ENV_VAR as ENV_VAR
from ._locations import HIDE_ENV_VAR as HIDE_ENV_VAR
from ._locations import DatasetFormatError as DatasetFormatError
from ._locations import DatasetNotFoundError as DatasetNotFoundError
from ._locations import default_cache_dir as default_cache_dir
from ._locations import default_data_dirs as default_data_dirs
from ._record import Record as Record
from ._silverbox import SILVERBOX_N_INIT as SILVERBOX_N_INIT
from ._silverbox import SILVERBOX_TS as SILVERBOX_TS
from ._silverbox import Silverbox as Silverbox
from ._silverbox import load_silverbox as load_silverbox
from ._wiener_hammerstein import WH_N_INIT as WH_N_INIT
from ._wiener_hammerstein import WienerHammerstein as WienerHammerstein
from ._wiener_hammerstein import load_wiener_hammerstein as load_wiener_hammerstein

__all__ = [
    "CACHE_ENV_VAR",
    "ENV_VAR",
    "HIDE_ENV_VAR",
    "URL_ENV_VAR",
    "EMPS_IDIM_LS_REFERENCE",
    "EMPS_N_INIT",
    "TANKS_N_INIT",
    "SILVERBOX_N_INIT",
    "SILVERBOX_TS",
    "WH_N_INIT",
    "Record",
    "EMPS",
    "EMPSRecord",
    "CascadedTanks",
    "Silverbox",
    "WienerHammerstein",
    "DatasetNotFoundError",
    "DatasetFormatError",
    "DatasetDownloadError",
    "DatasetChecksumError",
    "load_emps",
    "load_cascaded_tanks",
    "load_silverbox",
    "load_wiener_hammerstein",
    "default_data_dirs",
    "default_cache_dir",
]
