"""Data normalisation: what `check_data` builds from data it has checked.

Several trajectories of different lengths T_i (lists of arrays) become one (N, T_max, c)
array, each padded by repeating its last row; the padded samples, and in
`missing="mask"` mode the NaN samples of z, are masked out of the cost (a `Mask`:
eq. 5 then sums over the measured samples only, and divides by the number of time points
of the unpadded records, NaN samples included). The
checks themselves (shapes, channels, finiteness) stay in `_checks.check_data`, which calls
these functions in the order that keeps its errors in the order of the arguments.
"""

import numpy as np

from ._cost import Mask


def is_ragged(a) -> bool:
    """A list or tuple of per-trajectory arrays whose lengths differ."""
    if not isinstance(a, (list, tuple)) or not a:
        return False
    try:
        lengths = {np.shape(item)[0] for item in a if np.ndim(item) >= 1}
    except (TypeError, ValueError):
        return False
    return len(lengths) > 1


def pad(arrays, dtype) -> tuple[np.ndarray, tuple[int, ...]]:
    """Checked per-trajectory arrays (T_i, c) as one (N, T_max, c) array, each padded by
    repeating its last row, and the lengths T_i."""
    T = max(a.shape[0] for a in arrays)
    padded = np.stack(
        [
            np.concatenate([np.asarray(a), np.repeat(np.asarray(a)[-1:], T - a.shape[0], 0)])
            for a in arrays
        ]
    ).astype(dtype)
    return padded, tuple(a.shape[0] for a in arrays)


def fill_missing(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """z with its NaN samples set to 0, and where it is measured (not NaN)."""
    observed = ~np.isnan(z)
    return np.where(observed, z, 0.0).astype(z.dtype), observed


def sample_mask(shape, dtype, lengths, observed) -> Mask | None:
    """The `Mask` (of `dtype`) of z of `shape` (*N, T, n_z): the samples within each
    trajectory's length (`lengths`, None when all have T) that are measured (`observed`,
    None when all are); None when every sample counts."""
    traced = observed is not None and not isinstance(observed, np.ndarray)
    if lengths is None and (observed is None or (not traced and observed.all())):
        return None
    T = shape[-2]
    samples = np.ones(shape[:-1], np.float64)
    if lengths is not None:
        samples = (np.arange(T)[None, :] < np.asarray(lengths)[:, None]).astype(np.float64)
    outputs = samples[..., None] * np.ones(shape, np.float64)
    if observed is not None:
        outputs = outputs * observed
    return Mask(outputs.astype(dtype), samples.astype(dtype))
