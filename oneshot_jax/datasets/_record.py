"""`Record`: one input-output record, the type every loader returns for the community's
protocol, convertible to and from `nonlinear_benchmarks.Input_output_data`."""

from __future__ import annotations

import dataclasses
import numbers

import numpy as np

from .._counts import integral, real
from ..metrics import benchmark_scores


def _series(value, name):
    if np.iscomplexobj(value):
        raise TypeError(f"`{name}` must hold real numbers, got complex values.")
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"`{name}` must be a numeric array of shape (T,) or (T, channels), got "
            f"{type(value).__name__} ({err})."
        ) from err
    if a.ndim not in (1, 2):
        raise ValueError(f"`{name}` must have shape (T,) or (T, channels), got shape {a.shape}.")
    if not np.all(np.isfinite(a)):
        k = int(np.flatnonzero(~np.isfinite(a).reshape(a.shape[0], -1).all(axis=1))[0])
        raise ValueError(
            f"`{name}` must be finite (measured samples), got {a[k]} at sample {k}; fill the "
            "gaps of a record with missing samples before building a `Record`."
        )
    return a


@dataclasses.dataclass(frozen=True)
class Record:
    """One input-output record under the benchmark protocol of Champneys et al. (2024):
    a model may use the whole input `u` and only the first `n` outputs `y[:n]`; it is
    scored on `y[n:]` (see `oneshot_jax.metrics.benchmark_scores`).

    **Fields:**

    - `u`: input, float64 array of shape (T,) or (T, n_u).
    - `y`: output, float64 array of shape (T,) or (T, n_y).
    - `Ts`: sampling time in s, or None for a discrete-time record.
    - `n`: number of initial outputs a model may use (the protocol's state-initialisation
        window), at most T - 2 (the protocol scores at least two outputs); 0 for a
        training record, where every output may be used.
    - `name`: a short label, e.g. `"test WH"`.

    Unpacks as `u, y = record`. The aliases `sampling_time` and
    `state_initialization_window_length` read like `nonlinear_benchmarks.Input_output_data`.

    **Reference:**

    M. D. Champneys, G. I. Beintema, R. Tóth, M. Schoukens, T. J. Rogers, "Baseline results
    for selected nonlinear system identification benchmarks", arXiv:2405.10779, 2024.
    """

    u: np.ndarray
    y: np.ndarray
    Ts: float | None
    n: int = 0
    name: str = ""

    def __post_init__(self):
        u, y = _series(self.u, "u"), _series(self.y, "y")
        if u.shape[0] != y.shape[0]:
            raise ValueError(
                f"`u` and `y` must have the same number of samples, got {u.shape[0]} and "
                f"{y.shape[0]}."
            )
        if u.shape[0] < 1:
            raise ValueError("`u` and `y` must hold at least one sample, got 0.")
        Ts = real(self.Ts)  # (a 0-d array: the number it holds)
        if Ts is not None:
            if isinstance(Ts, bool) or not isinstance(Ts, numbers.Real):
                raise TypeError(
                    f"`Ts` must be a positive number (s) or None, got {type(Ts).__name__}."
                )
            Ts = float(Ts)
            if not (np.isfinite(Ts) and Ts > 0):
                raise ValueError(f"`Ts` must be a positive finite sampling time (s), got {Ts}.")
        n = integral(self.n)  # (20.0 or a 0-d array: the count it holds)
        if isinstance(n, bool) or not isinstance(n, numbers.Integral):
            raise TypeError(f"`n` must be an integer, got {type(n).__name__}.")
        n = int(n)
        if not (n == 0 or 0 < n <= y.shape[0] - 2):  # (`score` needs two samples scored)
            raise ValueError(
                f"`n` must be 0 or satisfy 0 < n <= T - 2 = {y.shape[0] - 2} (the number of "
                f"initial outputs a model may use; the protocol scores at least two), got {n}."
            )
        if not isinstance(self.name, str):
            raise TypeError(f"`name` must be a string, got {type(self.name).__name__}.")
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "Ts", Ts)
        object.__setattr__(self, "n", n)

    def __len__(self):
        return self.y.shape[0]

    def __iter__(self):
        yield self.u
        yield self.y

    def __repr__(self):
        Ts = "discrete time" if self.Ts is None else f"Ts={self.Ts:.6g} s"
        return (
            f"Record({self.name!r}, u.shape={self.u.shape}, y.shape={self.y.shape}, {Ts}, "
            f"n={self.n})"
        )

    # ------------------------------------------------------------------ protocol views

    @property
    def t(self) -> np.ndarray:
        """Sample times `Ts * arange(T)`, s (a `ValueError` for a discrete-time record)."""
        if self.Ts is None:
            raise ValueError(f"{self.name or 'this record'} is discrete-time (Ts is None).")
        return self.Ts * np.arange(len(self))

    @property
    def y_head(self) -> np.ndarray:
        """The outputs a model may use: `y[:n]`."""
        return self.y[: self.n]

    @property
    def sampling_time(self) -> float | None:
        """Alias of `Ts` (the name used by `nonlinear_benchmarks`)."""
        return self.Ts

    @property
    def state_initialization_window_length(self) -> int:
        """Alias of `n` (the name used by `nonlinear_benchmarks`)."""
        return self.n

    def score(self, yhat):
        """The protocol's scores of a model output on this record:
        `oneshot_jax.metrics.benchmark_scores(self.y, yhat, self.n)`.

        **Arguments:**

        - `yhat`: model output, same shape as `y`, computed from `u` and `y[:n]` only.

        **Returns:**

        A `oneshot_jax.metrics.BenchmarkScores` (RMSE, NRMSE, R², FIT per output over
        samples n:).
        """
        return benchmark_scores(self.y, yhat, self.n)

    def atleast_2d(self) -> Record:
        """The same record with `u` and `y` of shape (T, channels)."""
        return dataclasses.replace(
            self,
            u=self.u if self.u.ndim == 2 else self.u[:, None],
            y=self.y if self.y.ndim == 2 else self.y[:, None],
        )

    # ------------------------------------------------------------------ conversions

    @classmethod
    def from_nonlinear_benchmarks(cls, data, *, n=None, name=None) -> Record:
        """A `Record` from a `nonlinear_benchmarks.Input_output_data` (or any object with
        `u`, `y`, `sampling_time`, `state_initialization_window_length` and `name`).

        **Arguments:**

        - `data`: the object, e.g. one of `nonlinear_benchmarks.Silverbox()`'s test sets.
        - `n`: overrides its `state_initialization_window_length` (None there means 0).
        - `name`: overrides its name.

        **Returns:**

        A `Record` holding float64 copies of its arrays.
        """
        if isinstance(data, Record):
            rec = data
        else:
            missing = [a for a in ("u", "y") if not hasattr(data, a)]
            if missing:
                raise TypeError(
                    f"`data` must be a nonlinear_benchmarks.Input_output_data (with attributes "
                    f"u, y, sampling_time, state_initialization_window_length), got "
                    f"{type(data).__name__} without {', '.join(missing)}."
                )
            init = getattr(data, "state_initialization_window_length", None)
            rec = cls(
                u=np.array(data.u, dtype=np.float64),
                y=np.array(data.y, dtype=np.float64),
                Ts=getattr(data, "sampling_time", None),
                n=0 if init is None else init,
                name=getattr(data, "name", "") or "",
            )
        changes = {}
        if n is not None:
            changes["n"] = n
        if name is not None:
            changes["name"] = name
        return dataclasses.replace(rec, **changes) if changes else rec

    def to_nonlinear_benchmarks(self):
        """This record as a `nonlinear_benchmarks.Input_output_data` (n = 0 becomes None),
        e.g. to score it with `nonlinear_benchmarks.error_metrics`.

        **Raises:**

        `ImportError` with the install command when `nonlinear_benchmarks` is missing.
        """
        try:
            from nonlinear_benchmarks import Input_output_data
        except ImportError as err:
            raise ImportError(
                "Record.to_nonlinear_benchmarks needs the `nonlinear_benchmarks` package: "
                "pip install nonlinear-benchmarks"
            ) from err
        return Input_output_data(
            u=self.u,
            y=self.y,
            sampling_time=self.Ts,
            name=self.name,
            state_initialization_window_length=self.n or None,
        )


def split_record(full: Record, start, stop, *, n=0, name="") -> Record:
    """`full[start:stop]` as a new `Record` (views of its arrays) with its own `n` and name."""
    return Record(u=full.u[start:stop], y=full.y[start:stop], Ts=full.Ts, n=n, name=name)
