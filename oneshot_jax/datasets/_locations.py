"""Where the loaders look for a benchmark's files, and the two error types: the bottom of
`oneshot_jax.datasets` (the download and the readers build on it)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

ENV_VAR = "ONESHOT_JAX_DATA"
"""Environment variable naming a data folder (holding `emps/`, `cascaded_tanks/`,
`silverbox/`, `wiener_hammerstein/`, or the files themselves)."""

CACHE_ENV_VAR = "ONESHOT_JAX_CACHE"
"""Environment variable naming the folder that `download=True` fetches into."""

HIDE_ENV_VAR = "ONESHOT_JAX_HIDE_DATA"
"""Environment variable that, set to `1`, hides the folders the loaders would find on their
own (`shared/data` beside the repository or the working directory, and the user cache
folder unless `$ONESHOT_JAX_CACHE` names it), as on a fresh checkout. `path=`,
`$ONESHOT_JAX_DATA`, `$ONESHOT_JAX_CACHE`, `cache_dir=` and `download=True` still work."""


def data_hidden() -> bool:
    """Whether `$ONESHOT_JAX_HIDE_DATA` is set to a true value (`1`, `true`, `yes`, `on`)."""
    return os.environ.get(HIDE_ENV_VAR, "").strip().lower() in ("1", "true", "yes", "on")


class DatasetNotFoundError(FileNotFoundError):
    """The benchmark's files were not found in any of the searched places."""


class DatasetFormatError(ValueError):
    """A benchmark file exists but does not hold what the loader expects."""


def default_cache_dir() -> Path:
    """The folder that `download=True` fetches into: `$ONESHOT_JAX_CACHE` when set, else
    the user cache folder (`$XDG_CACHE_HOME/oneshot_jax` or `~/.cache/oneshot_jax` on
    Linux, `~/Library/Caches/oneshot_jax` on macOS, `%LOCALAPPDATA%\\oneshot_jax\\Cache` on
    Windows). It holds one subfolder per benchmark (`emps/`, `cascaded_tanks/`, ...)."""
    env = os.environ.get(CACHE_ENV_VAR)
    if env:
        return Path(env).expanduser()
    if sys.platform == "win32" and os.environ.get("LOCALAPPDATA"):
        return Path(os.environ["LOCALAPPDATA"]) / "oneshot_jax" / "Cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "oneshot_jax"
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "oneshot_jax"


def default_data_dirs() -> list[Path]:
    """Data roots searched when no `path` is given, in order: `$ONESHOT_JAX_DATA` when set,
    then the `shared/data` folders beside the repository and beside the working directory
    that exist, then the download cache (`default_cache_dir()`) when it exists.

    With `$ONESHOT_JAX_HIDE_DATA=1` only the folders named by `$ONESHOT_JAX_DATA` and
    `$ONESHOT_JAX_CACHE` are searched, as on a fresh checkout without the data."""
    out = []
    env = os.environ.get(ENV_VAR)
    if env:
        out.append(Path(env).expanduser())
    if data_hidden():
        found = [default_cache_dir()] if os.environ.get(CACHE_ENV_VAR) else []
    else:
        # (the checkout's parent: oneshot_jax/datasets/_locations.py three folders up; a
        # package installed right under the root has none)
        parents = Path(__file__).resolve().parents
        beside = [parents[3] / "shared" / "data"] if len(parents) > 3 else []
        found = [*beside, Path.cwd().resolve().parent / "shared" / "data", default_cache_dir()]
    for p in found:
        if p.is_dir() and all(p.resolve() != q.resolve() for q in out):
            out.append(p)
    return out


def candidates(path, subdirs) -> list[Path]:
    """Folders to look in: for each root (the given path, else `default_data_dirs()`), its
    `subdirs` (relative paths, e.g. `silverbox`, `silverbox/SilverboxFiles`), then the root
    itself."""
    roots = [Path(path).expanduser()] if path is not None else default_data_dirs()
    out = []
    for r in roots:
        out.extend([*(r / s for s in subdirs), r])
    return out


def find_folder(dirs, alternatives):
    """The first folder of `dirs` holding every file of one of the `alternatives` (tuples
    of file names, in order of preference), as `(folder, files)`, else `(None, None)`."""
    for d in dirs:
        for names in alternatives:
            if all((d / f).is_file() for f in names):
                return d, names
    return None, None
