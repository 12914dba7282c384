"""NumPy masked arrays given where an array is read: their data where nothing is masked, a
refusal where something is (converting one to NumPy or JAX drops its mask, and the masked
values would count as data). `_checks` reads the arguments of `fit` and its kin with it,
`metrics` its scores' inputs.
"""

import numpy as np


def unmasked(a, name, measured=False):
    """The data of a NumPy masked array none of whose entries is masked (`a` itself if it
    is not one). A masked entry is refused: converting the array to one of NumPy or JAX
    would drop its mask, and the masked values would count as data."""
    if not isinstance(a, np.ma.MaskedArray):
        return a
    if not np.ma.is_masked(a):
        return np.ma.getdata(a)
    count = int(np.ma.count_masked(a))
    how = (
        f'pass `{name}.filled(np.nan)` with `missing="mask"` (a NaN output is a missing sample)'
        if measured
        else "fill them (`.filled(value)`): every entry here is used"
    )
    raise ValueError(
        f"`{name}` is a NumPy masked array with {count} masked entries, and its mask would be "
        f"ignored: {how}."
    )
