"""JAX's persistent compilation cache, turned on by one call.

A fresh process compiles every configuration of `fit` (model, shapes, solver, options)
once: seconds for a small model (see `benchmarks/first_call.py`). JAX can keep the
compiled executables on disk and load them in later processes, which then skip XLA's
compilation (tracing the model still runs). The library never changes JAX's
configuration by itself; `enable_compilation_cache` is the one call that does.
"""

from pathlib import Path

import jax

from ._checks import check_path
from .datasets._locations import default_cache_dir


def enable_compilation_cache(
    path: str | Path | None = None, *, min_compile_time_secs: float = 0.0
) -> Path:
    """Turn on JAX's persistent compilation cache for this process, so that a later
    process with the same configurations of `fit`, `predict`, `simulate`, ... loads the
    compiled code instead of compiling it again.

    It sets JAX's global configuration (for every JAX computation of the process, not
    only this library's): `jax_compilation_cache_dir` to `path`,
    `jax_persistent_cache_min_compile_time_secs` to `min_compile_time_secs` and
    `jax_persistent_cache_min_entry_size_bytes` to 0 (cache whatever compiled, however
    small). Call it once, at the start of a script or notebook; importing `oneshot_jax`
    changes nothing.

    An entry is reused only by the same JAX and jaxlib versions on the same kind of
    device, for the same compiled program (the same model code, shapes, dtypes, solver
    and options). The cache is never pruned: delete the folder to empty it. Like any
    cache of executable code it is trusted: do not share the folder with users you do not
    trust (see JAX's "Persistent compilation cache" guide).

    **Arguments:**

    - `path`: the cache folder (created if missing). Default: `jax/` in the library's
        user cache folder, `$ONESHOT_JAX_CACHE/jax` when that variable is set, else e.g.
        `~/.cache/oneshot_jax/jax` on Linux (`oneshot_jax.datasets.default_cache_dir()`).
    - `min_compile_time_secs`: only programs that took at least this long to compile are
        written (JAX's default is 1 second, which would leave out the small compiled
        pieces of `predict` and `simulate`).

    **Returns:**

    The cache folder, as an absolute `pathlib.Path`.

    **Example:**

    ```python
    import oneshot_jax as oj

    oj.enable_compilation_cache()  # before the first fit of the process
    result = oj.fit(model, theta0, x0, u, z)  # compiled once, loaded in later processes
    ```
    """
    check_path(path, what="the cache folder")
    try:
        folder = Path(default_cache_dir() / "jax" if path is None else path).expanduser()
        folder = folder.resolve()
    except (TypeError, ValueError, OSError) as err:
        raise ValueError(f"`path`: {path!r} is not a usable folder path ({err}).") from None
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"`path` must be a folder, got the file {str(folder)!r}.")
    try:
        seconds = (
            float("nan")
            if isinstance(min_compile_time_secs, (bool, str, bytes))
            else float(min_compile_time_secs)
        )
    except (TypeError, ValueError):
        seconds = float("nan")
    if not seconds >= 0.0 or seconds == float("inf"):
        raise ValueError(
            f"`min_compile_time_secs` must be a finite number >= 0, got {min_compile_time_secs!r}."
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(
            f"`path`: cannot create the cache folder {str(folder)!r} ({err})."
        ) from None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", seconds)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder
