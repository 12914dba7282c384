"""The warnings of the fits a driver runs, shown at the driver's caller.

`fit` points its warnings at the line that called it (`stacklevel`). Inside a driver
(`fit_continuation`, `check_basin`, `fit_physics_first`, `fit_orthogonal`) that line is
the driver's own, in a library file; `at_caller` warns again from the driver's caller, as
a plain `fit` does. A warning raised elsewhere (the user's model, another library) keeps
its own line, module and filters.
"""

import contextlib
import os
import warnings


def _same_file(a, b) -> bool:
    return os.path.normcase(os.path.abspath(a)) == os.path.normcase(os.path.abspath(b))


@contextlib.contextmanager
def at_caller(driver_file):
    """Record the warnings raised in the block; on leaving it (also when the block raises),
    raise those that point at `driver_file` (the driver's module, `__file__`) again at the
    caller of the function that holds the `with` statement, and show the others as they
    were. The user's filters decide every warning at its own line, as without the driver:
    those pointed at the driver again at the caller's."""
    caught = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            # (no filter of its own: recording replaces only the display)
            yield
    finally:
        for w in caught:
            if _same_file(w.filename, driver_file):
                # (1: here, 2: contextlib's __exit__, 3: the driver, 4: its caller)
                warnings.warn(w.message, w.category, stacklevel=4)
            else:  # (the filters passed it at its own line: shown, not decided again)
                warnings.showwarning(w.message, w.category, w.filename, w.lineno, w.file, w.line)
