"""Counts given as integers: an int, a NumPy integer, or an integral float (10.0, as a
configuration file may write it), never a bool."""

import math
import numbers

import numpy as np


def is_count(value, least) -> bool:
    """Whether `value` is an integer >= `least`: an int, a NumPy integer or an integral
    float, not a bool."""
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
    if is_count(value, 0):
        return int(value)
    return value
