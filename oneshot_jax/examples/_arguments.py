"""The example builders' checks of their own arguments: a count or a width that the
builder converts itself (`int(...)`, `float(...)`) is checked first, so that 2.7 steps or
a width of 0 is refused naming the argument, not truncated or turned into NaN."""

import math
import numbers

import numpy as np


def is_count(value, least) -> bool:
    """Whether `value` is an integer (not a bool) of at least `least`."""
    ok = not isinstance(value, (bool, np.bool_)) and isinstance(value, numbers.Integral)
    return ok and value >= least


def count(value, name, least=1) -> int:
    """`value` as an int, or a ValueError naming `name` unless it is an integer >= least."""
    if not is_count(value, least):
        raise ValueError(f"`{name}` must be an integer >= {least}, got {value!r}.")
    return int(value)


def positive(value, name) -> float:
    """`value` as a float, or a ValueError naming `name` unless it is a finite number > 0."""
    ok = not isinstance(value, (bool, np.bool_)) and isinstance(value, numbers.Real)
    if not (ok and math.isfinite(value) and value > 0):
        raise ValueError(f"`{name}` must be a finite number > 0, got {value!r}.")
    return float(value)
