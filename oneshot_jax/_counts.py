"""Counts given as integers: an int, a NumPy integer, or an integral float (10.0, as a
configuration file may write it), never a bool."""

import math
import numbers

import numpy as np


def real(value):
    """A number given as a concrete 0-d array (NumPy or JAX, of a real dtype) or a NumPy
    scalar as the Python number it holds (equinox takes a NumPy scalar in a static field
    for an array, and warns); anything else (a Python number, a schedule, a wrong value)
    as given, for the caller's check to accept or refuse by name. The converter of the
    solvers' real options."""
    if (
        (isinstance(value, (np.ndarray, np.generic)) or type(value).__module__.startswith("jax"))
        and getattr(value, "ndim", None) == 0
        and getattr(value, "dtype", np.dtype(object)).kind in "iuf"
    ):
        try:
            return value.item()
        except Exception:  # noqa: BLE001 - a tracer: left as given
            return value
    return value


def is_count(value, least) -> bool:
    """Whether `value` is an integer >= `least`: an int, a NumPy integer or an integral
    float, not a bool."""
    value = real(value)
    return (
        isinstance(value, numbers.Real)
        and not isinstance(value, (bool, np.bool_))
        and math.isfinite(value)
        and int(value) == value
        and value >= least
    )


def integral(value):
    """A count given as an integral float (10.0, as a configuration file may write it) as
    the int it is; anything else as given, for the caller's check to accept or refuse by
    name. The converter of the count options of solvers and `Validation`."""
    value = real(value)
    if is_count(value, 0):
        return int(value)
    return value
