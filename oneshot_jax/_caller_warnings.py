"""The library's warnings: raised (`warn`), kept with a fit's result (`recording`), and
those of the fits a driver runs shown at the driver's caller (`at_caller`).

Every warning of the library goes through `warn`, which also hands its message to the
`recording` blocks around it: `fit` keeps those of its own run in `FitResult.warnings`,
which its printout shows, whatever the user's filters display.

`fit` points its warnings at the line that called it (`stacklevel`). Inside a driver
(`fit_continuation`, `check_basin`, `fit_physics_first`, `fit_orthogonal`) that line is
the driver's own, in a library file; `at_caller` warns again from the driver's caller, as
a plain `fit` does. A warning raised elsewhere (the user's model, another library) keeps
its own line, module and filters.
"""

import contextlib
import contextvars
import os
import sys
import warnings

import equinox as eqx

# This library's files and equinox's (the wrappers around a module's bound methods).
_LIBRARY_DIRS = tuple(os.path.dirname(m.__file__) + os.sep for m in (sys.modules[__package__], eqx))


def frames_to_user() -> int:
    """The frames between the caller of this function's caller and the user's code: the
    wrappers equinox puts around a module's bound methods, and this library's functions
    on the way (`plot.compare` calling a method, `simulate` calling the checks), so that
    a warning points at the user's line (`warn(..., stacklevel=2 + frames_to_user())`
    from the function that warns)."""
    frame, count = sys._getframe(2), 0
    while frame is not None and frame.f_code.co_filename.startswith(_LIBRARY_DIRS):
        frame, count = frame.f_back, count + 1
    return count


def _same_file(a, b) -> bool:
    return os.path.normcase(os.path.abspath(a)) == os.path.normcase(os.path.abspath(b))


@contextlib.contextmanager
def at_caller(driver_file, skip=0):
    """Record the warnings raised in the block; on leaving it (also when the block raises),
    raise those that point at `driver_file` (the driver's module, `__file__`) again at the
    caller of the function that holds the `with` statement (`skip` frames further out:
    the wrappers equinox puts around a module's bound methods), and show the others as
    they were. The user's filters decide every warning at its own line, as without the
    driver: those pointed at the driver again at the caller's."""
    caught = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            # (no filter of its own: recording replaces only the display)
            yield
    finally:
        for w in caught:
            if _same_file(w.filename, driver_file):
                # (1: here, 2: contextlib's __exit__, 3: the driver, 4: its caller)
                warnings.warn(w.message, w.category, stacklevel=4 + skip)
            else:  # (the filters passed it at its own line: shown, not decided again)
                warnings.showwarning(w.message, w.category, w.filename, w.lineno, w.file, w.line)


class _Record:
    """The messages of the warnings raised through `warn` while a `recording` block runs,
    in order, each once."""

    def __init__(self):
        self.messages: list[str] = []

    def add(self, message: str):
        if message not in self.messages:
            self.messages.append(message)


_RECORDS: contextvars.ContextVar[tuple] = contextvars.ContextVar("oneshot_jax_records", default=())


@contextlib.contextmanager
def recording():
    """Record the messages of the warnings the library raises (`warn`) in the block,
    whatever the user's filters show or hide: `fit` keeps them in its result
    (`FitResult.warnings`, printed with it). A block inside another records into both."""
    record = _Record()
    token = _RECORDS.set((*_RECORDS.get(), record))
    try:
        yield record
    finally:
        _RECORDS.reset(token)


@contextlib.contextmanager
def unrecorded():
    """The block's warnings reach no `recording` block around it: the fits of a driver
    that re-raises the warnings it keeps (`weight="noise"`: those of its returned fit
    alone, not of the rounds before it)."""
    token = _RECORDS.set(())
    try:
        yield
    finally:
        _RECORDS.reset(token)


def warn(message, category=UserWarning, stacklevel=1, *, kept=True):
    """`warnings.warn` for the library's own warnings: the message is also kept by every
    `recording` block around the call (not with `kept=False`: a warning of the user's
    model or of another library, raised again at the caller's line). `stacklevel` counts
    from the caller, as for `warnings.warn`."""
    if kept:
        for record in _RECORDS.get():
            record.add(str(message))
    warnings.warn(message, category, stacklevel=stacklevel + 1)


def warn_each_time(message, category, filename):
    """`warn` where no caller's line is known (a host callback of compiled code, at the
    line `filename`:0): with a registry of its own, so that the filters' "default" shows
    every such warning, not the first alone (all of them come from one line)."""
    for record in _RECORDS.get():
        record.add(str(message))
    warnings.warn_explicit(message, category, filename, 0, registry={})
