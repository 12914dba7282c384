"""The warnings of the fits a driver runs, shown at the driver's caller.

`fit` points its warnings at the line that called it (`stacklevel`). Inside a driver
(`fit_continuation`, `check_basin`, `fit_physics_first`, `fit_orthogonal`) that line is
the driver's own, in a library file; `at_caller` records them and warns again from the
driver's caller, as a plain `fit` does.
"""

import contextlib
import warnings


@contextlib.contextmanager
def at_caller():
    """Record the warnings raised in the block, then raise them again (also when the block
    raises) at the caller of the function that holds the `with` statement. The user's
    filters apply then, once, at that line."""
    caught = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
    finally:
        for w in caught:
            # (1: here, 2: contextlib's __exit__, 3: the driver, 4: its caller)
            warnings.warn(w.message, w.category, stacklevel=4)
