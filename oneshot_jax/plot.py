"""The figures a MATLAB user draws right after a fit: `compare`, the measured outputs
against the simulated or predicted outputs of one or several models with their FIT %,
`resid`, the residual analysis with its 99 % bounds, and `bode`, the frequency response
of a linearised model.

matplotlib is an optional dependency (`pip install matplotlib`; from a checkout,
`pip install -e ".[plot]"`, the `plot` extra). It is imported
when a figure is drawn, never by `import oneshot_jax`; the functions use `pyplot`, so the
figure shows in a notebook or a window as usual, and return it (`fig.savefig(...)`).
"""

from __future__ import annotations

import numbers
import statistics

import numpy as np

from . import metrics
from ._ahead import AheadPrediction
from ._caller_warnings import frames_to_user, warn
from ._counts import integral
from ._fit_result import FitResult, is_fitted_record
from ._initial_state import Prediction, several_records
from ._model import ODE_STEPS, model_labels
from ._operating_point import LinearModel, frequencies
from ._timing import as_times as _as_times

__all__ = ["bode", "compare", "resid"]


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise ImportError(
            "oneshot_jax.plot draws with matplotlib, which is not installed: pip install "
            'matplotlib (from a checkout of oneshot_jax, pip install -e ".[plot]", the `plot` '
            "extra)."
        ) from err
    return plt


def _columns(a, name):
    """`a` as a float64 (T, n) array."""
    if several_records(a):
        raise ValueError(
            f"`{name}` must have shape (T,) or (T, n) (one record), got a "
            f"{type(a).__name__} of {len(a)} records. Compare them one at a time, e.g. "
            "`compare(z[i], result, u=u[i], n=n)`."
        )
    try:
        complex_ = np.iscomplexobj(a)
        a = a if complex_ else np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"`{name}` must be a numeric array, got {type(a).__name__}.") from err
    if complex_:  # (a cast would drop the imaginary part)
        raise ValueError(f"`{name}` must hold real numbers, got dtype {np.asarray(a).dtype}.")
    if a.ndim == 3:  # (several records: MATLAB's compare shows them one at a time too)
        raise ValueError(
            f"`{name}` must have shape (T,) or (T, n) (one record), got {a.shape}: "
            f"{a.shape[0]} records. Compare them one at a time, e.g. "
            "`compare(z[i], result, u=u[i], n=n)`, or with the predictions of "
            "`result.predict(u, z[:, :n])` (one per record): `compare(z[i], preds[i], n=n)`."
        )
    if a.ndim not in (1, 2):
        raise ValueError(f"`{name}` must have shape (T,) or (T, n) (one record), got {a.shape}.")
    return a[:, None] if a.ndim == 1 else a


def _axes(ax, count, plt, figsize, what="one per output"):
    """`count` Axes: new ones in a column, or those of `ax` (one Axes or a sequence)."""
    if ax is None:
        fig, axes = plt.subplots(count, 1, sharex=True, squeeze=False, figsize=figsize)
        return fig, list(axes[:, 0])
    axes = list(np.ravel(np.asarray(ax, dtype=object)))
    if len(axes) != count or not all(hasattr(a, "plot") for a in axes):
        raise ValueError(f"`ax` must be {count} matplotlib Axes ({what}), got {ax!r}.")
    return axes[0].figure, axes


def _warn_other_record(name, result, zhat, z):
    """Warn where a one-record `FitResult` is simulated from its fitted x0 on a record
    that is not the one it was fitted on (`_fit_result.is_fitted_record`): MATLAB's
    `compare` estimates the initial state, and a user who expects it reads a FIT% of
    the wrong initial state."""
    if is_fitted_record(result, zhat, z):
        return
    warn(
        f"`{name}` is simulated from the x0 fitted on its own data, which is not this "
        "record: pass `n` (e.g. n=20) to estimate x0 from the first n samples of `z`, as "
        "the benchmark protocol does (MATLAB's compare estimates it from the whole record: "
        "pass `result.predict(u, z)`'s output for that).",
        stacklevel=4,
    )


def _warn_other_head(name, prediction, z):
    """Warn where a `Prediction` was made from the first n outputs of a record other
    than `z` (its `X0Estimate.head` differs from z[:n]): its FIT would score one record's
    prediction against another record (a list of per-record predictions passed whole)."""
    head = getattr(prediction.estimate, "head", None)
    if head is None:
        return
    head = np.asarray(head, np.float64)
    head = head.reshape(head.shape[0], -1) if head.ndim else head
    if head.ndim != 2 or head.shape[1] != z.shape[1] or head.shape[0] > z.shape[0]:
        return  # (a shape mismatch is refused with the model's output)
    ours = z[: head.shape[0]]
    scale = np.nanmax(np.abs(ours), initial=0.0)
    if np.array_equal(np.isnan(head), np.isnan(ours)) and np.allclose(
        head, ours, rtol=1e-6, atol=1e-6 * scale, equal_nan=True
    ):
        return
    warn(
        f"`{name}` is a Prediction made from the first {head.shape[0]} outputs of another "
        "record (they differ from those of `z`): its FIT scores that record's prediction "
        "against this one. Pass the Prediction of this record (`predictions[i]` for "
        "record i).",
        stacklevel=4,
    )


def _fixed_dt(result):
    """The `dt` of a FitResult's `Model.from_ode` model with a fixed sample interval, else
    None."""
    step = getattr(getattr(result, "model", None), "step", None)
    return getattr(step, "dt", None) if isinstance(step, ODE_STEPS) else None


def _model_dt(models):
    """The sample interval the FitResults among `models` share (`_fixed_dt`), for the time
    axis; None where one has none or they differ."""
    dts = {_fixed_dt(m) for m in models if isinstance(m, FitResult)}
    if len(dts) != 1 or None in dts:
        return None
    return float(dts.pop())


def _check_sample_interval(name, result, Ts):
    """Refuse a record sampled at `Ts` for a FitResult of a `Model.from_ode` model with
    another fixed `dt`: its step advances dt per sample, so the simulation would run on
    the wrong time scale (MATLAB's compare simulates a continuous-time model at the
    data's Ts)."""
    dt = _fixed_dt(result)
    if Ts is None or dt is None or np.isclose(float(Ts), float(dt), rtol=1e-9, atol=0.0):
        return
    raise ValueError(
        f"the record is sampled at Ts = {float(Ts)!r}, but `{name}`'s model was built with "
        f"dt = {float(dt)!r} (`Model.from_ode(rhs, dt)` advances dt per sample): build the "
        f"model for this record, `Model.from_ode(rhs, dt={float(Ts)!r}, ...)`, and pass "
        "`oneshot_jax.predict(model, result.theta, u, z, n)`'s Prediction instead."
    )


def _model_output(i, model, u, z, n, t=None, Ts=None):
    """The output (T, n_z) of the i-th model: a FitResult's simulation (or its prediction
    from the first n samples; at the sample times `t` for a timed model), a Prediction's
    z, or the array itself."""
    name = f"models[{i}]"
    if isinstance(model, FitResult):
        if u is None:
            raise ValueError(f"`u` is required to simulate {name}, a FitResult.")
        _check_sample_interval(name, model, Ts)
        t = t if getattr(model.model, "timed", False) else None
        # Missing samples of the head (NaN) are left out of x0's fit, as of the FIT.
        gaps = {"missing": "mask"} if n and np.isnan(z[:n]).any() else {}
        # (a `window=` fit simulates from its window at sample 0: `FitResult.simulate`)
        several = np.ndim(model.x0) == 2 and model.window_starts is None
        if not n and several and np.ndim(u) == 2:
            raise ValueError(
                f"`{name}` was fitted on {np.shape(model.x0)[0]} trajectories, each from its "
                "own x0 (a row of its `x0`): to compare it with one record, pass `n` >= 1 (its "
                "initial state is then estimated from the record's first n outputs), or, "
                "for record i of the fit, its simulation from the fitted initial state, "
                "`result.simulate(u, x0=result.x0[i])[1]`, as the model output."
            )
        starts = model.window_starts
        if not n and starts is not None and np.ndim(u) == 2 and 0 not in np.asarray(starts):
            raise ValueError(
                f"`{name}` was fitted on windows (`window=`) none of which starts at sample 0, "
                "so it has no state for the record's start: pass `n` >= 1 (its initial state is "
                "then estimated from the record's first n outputs)."
            )
        zhat = model.predict(u, z[:n], t=t, **gaps).z if n else model.simulate(u, t=t)[1]
        if not n:
            _warn_other_record(name, model, np.asarray(zhat), z)
    elif isinstance(model, (Prediction, AheadPrediction)):
        if isinstance(model, Prediction):
            _warn_other_head(name, model, z)
        zhat = model.z
    else:
        zhat = model
    zhat = _columns(zhat, name)
    if zhat.shape != z.shape:
        hint = (
            " (a FitResult of several trajectories simulates each: pass `n` to predict this "
            "record from its head instead)"
            if isinstance(model, FitResult)
            and np.ndim(model.x0) == 2
            and model.window_starts is None
            and zhat.shape[-1] == z.shape[-1]
            else ""
        )
        raise ValueError(
            f"the output of `{name}` must have the shape of `z` {z.shape}, got {zhat.shape}{hint}."
        )
    bad = np.isfinite(z) & ~np.isfinite(zhat)
    predicted = isinstance(model, Prediction) or (isinstance(model, FitResult) and n)
    if bad.any() and not predicted:  # (`predict` warned of its own)
        first = int(np.argmax(bad.any(axis=1)))
        warn(
            f"the output of `{name}` is not finite at {int(bad.sum())} measured samples, the "
            f"first at sample {first} (the model leaves its domain or blows up on this "
            "record): its FIT is NaN.",
            RuntimeWarning,
            stacklevel=2 + frames_to_user(),
        )
    return zhat


def _band(model, u, z, n, t, confidence):
    """The half-width (T, n_z) of a FitResult's confidence band or of an AheadPrediction's
    prediction band (`compare`), NaN where its std is not known; None for another model
    or without `confidence`."""
    if confidence is None or not isinstance(model, (FitResult, AheadPrediction)):
        return None
    if isinstance(model, AheadPrediction):
        std = np.asarray(model.std, np.float64)
    else:
        t = t if getattr(model.model, "timed", False) else None
        std = model.output_std(u, z_head=z[:n] if n else z, t=t)
    q = statistics.NormalDist().inv_cdf(0.5 + 0.5 * confidence)
    return np.where(np.isfinite(std), q * std, np.nan)


def compare(
    z,
    *models,
    u=None,
    t=None,
    n=None,
    labels=None,
    ax=None,
    outputs=None,
    time_label=None,
    confidence=None,
):
    """Plot measured outputs against the outputs of one or several models, with each
    model's FIT % in the legend (MATLAB's `compare`).

    FIT = 100 (1 - ||zhat - z|| / ||z - mean(z)||) per output (`metrics.fit_percent`),
    over the samples n: when `n` is given, as the benchmark protocol scores: the first n
    samples, from which a model's initial state is estimated, are shaded and left out.

    **Arguments:**

    - `z`: the measured outputs, shape (T,) or (T, n_z) (NaN where missing), or a record
        with `u`, `y` (a `oneshot_jax.datasets.Record`): then `u`, `n` and the time axis
        (from `Ts`) default to the record's.
    - `models`: one or several (as arguments, or one list) of: a
        `FitResult`, simulated on `u` from its fitted x0
        (the data it was fitted on, or a record from the same initial state; on another
        record it warns; after a `window=` fit, from the state of its window at sample
        0, as `FitResult.simulate`), or, with `n`, predicted from the first n samples of `z`
        (`FitResult.predict`, which estimates every entry of x0, also those the fit held;
        to hold those, pass the Prediction of
        `result.predict(u, z[:n], x0=known, estimate=result.x0_estimated)` instead;
        MATLAB's `compare` estimates the initial state too, but from the whole record,
        and scores every sample: pass the `z` of
        `result.predict(u, z)` for its numbers); a
        `Prediction` from `oneshot_jax.predict` (its `z`); an `AheadPrediction` from
        `predict_ahead` (its K-step-ahead `z`: MATLAB's `compare(data, sys, K)`); an
        array of model outputs shaped like `z`. A `Prediction` made from the head of
        another record than `z` warns.
    - `u`: the inputs (T,) or (T, n_u), needed to simulate a `FitResult`.
    - `t`: the time axis (T,); default the sample index (times `Ts` for a record, or
        the `dt` of the FitResults' `Model.from_ode` models where they share one). A
        `FitResult` of a model of time-stamped records (`Model.from_ode(rhs, dt=None)`)
        is simulated at these sample times.
    - `n`: the protocol's head: the number of first samples used for x0, left out of the
        FIT; an integer 0 <= n <= T - 2 (an integral float such as 20.0 counts). Default:
        none (the record's `n` for a record).
    - `labels`: one name per model; default `"model"` or `"model 1"`, `"model 2"`, ...
    - `ax`: matplotlib Axes to draw in, one per output; default a new figure.
    - `outputs`: one name per output for its axis, with its unit (`["q (mm)"]`;
        MATLAB's `OutputName` and `OutputUnit`); default the `outputs` of a FitResult's
        model (`Model(..., outputs=...)`), else `"output"` or `"output 0"`, ...
    - `time_label`: the time axis's label, with its unit (`"time (ms)"`; MATLAB's
        `TimeUnit`); default `"sample"`, `"time (s)"` for a record with `Ts`, and
        `"time"` for a given `t` or for FitResults of `Model.from_ode` models with one
        fixed `dt` (the axis k dt, in the model's time unit).
    - `confidence`: a level in (0, 1), e.g. 0.95: each `FitResult`'s confidence band
        of its output, zhat +- q std with q the normal quantile of (1 + confidence) / 2
        and std from `FitResult.output_std` (MATLAB's `showConfidence`): with `n`, of
        the prediction from the first n samples; without, x0 estimated from the whole
        record (on the fitted record, the joint covariance of theta and x0). Samples of
        unknown std (inf) get no band. An `AheadPrediction`'s band is its prediction
        band instead, zhat +- q std with its `std` (where a new measurement lies under
        the filter's noise model). Default: no band. The y-axis holds the measured and
        model outputs; a band reaching more than their range beyond them (the first K
        samples of a K-step prediction from a broad prior, say) is cut at the axis.

    **Returns:**

    The matplotlib `Figure`.

    **Raises:**

    `ImportError` without matplotlib (install the `plot` extra); `ValueError` naming the
    argument for a shape that does not match `z`, a missing `u`, `simulate`'s `(x, z)`
    passed whole as the models, or `n`, `t`, `labels`, `outputs` or `ax` that do not
    fit; `TypeError` for `labels`, `outputs` or `time_label` that are not strings.
    """
    plt = _pyplot()
    Ts = None
    if hasattr(z, "u") and hasattr(z, "y"):
        record = z
        z, Ts = record.y, getattr(record, "Ts", None)
        u = record.u if u is None else u
        n = getattr(record, "n", None) if n is None else n
    z = _columns(z, "z")
    T, n_z = z.shape

    results = (FitResult, Prediction, AheadPrediction)

    def one_model(m):  # (a result, or one output record of z's T samples)
        if isinstance(m, results):
            return True
        return hasattr(m, "shape") and np.ndim(m) in (1, 2) and np.shape(m)[0] == T

    if (
        len(models) == 1
        and isinstance(models[0], tuple)
        and len(models[0]) == 2
        and not any(isinstance(m, results) for m in models[0])
        and all(hasattr(m, "shape") or isinstance(m, (list, tuple)) for m in models[0])
    ):  # (the states would be drawn and scored as a model's outputs)
        raise ValueError(
            "`models` holds one tuple of two arrays: is it what `simulate` returns, the "
            "states and the outputs `(x, z)`? Pass the outputs (`result.simulate(u)[1]`); "
            "pass several model outputs as separate arguments or as a list."
        )
    if (
        len(models) == 1 and isinstance(models[0], (list, tuple)) and all(map(one_model, models[0]))
    ):  # (a list of models, as MATLAB's compare(data, sys1, sys2) users may pass them; a
        # list of output arrays was read as one array of several records)
        models = tuple(models[0])
    if not models:
        raise ValueError("`models` is empty: pass at least one model (or model output).")
    if n_z > T:
        warn(
            f"`z` holds T = {T} samples of {n_z} outputs, one axis per output: is it "
            f"transposed? `compare` takes samples along the first axis, shape (T, n_z).",
            UserWarning,
            stacklevel=2,
        )
    if u is not None:
        u = _columns(u, "u")
        if u.shape[0] != T:
            hint = (
                f" (`z` holds T = {T} samples of {n_z} outputs: is it transposed?)"
                if n_z == u.shape[0]
                else ""
            )
            raise ValueError(f"`u` must have the T = {T} samples of `z`, got {u.shape[0]}{hint}.")
    if n is not None:
        n = integral(n)  # (20.0, as a configuration file may write it, or a 0-d array)
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 0 <= n <= T - 2:
            raise ValueError(f"`n` must be an integer with 0 <= n <= T - 2 = {T - 2}, got {n!r}.")
        n = int(n)
    n = n or 0
    labels = _names(labels, len(models), "labels", "model", start=1)
    # (MATLAB's compare names the horizon of a K-step prediction)
    labels = [
        f"{label} ({m.K}-step ahead)" if isinstance(m, AheadPrediction) else label
        for m, label in zip(models, labels)
    ]
    if outputs is None:  # (the names of the first model that has them for these outputs)
        given = (
            getattr(m.model, "outputs", None) if isinstance(m, FitResult) else m.outputs
            for m in models
            if isinstance(m, (FitResult, AheadPrediction))
        )
        outputs = next((list(o) for o in given if model_labels(o, n_z) is not None), None)
    names = _names(outputs, n_z, "outputs", "output", start=0, of=" of `z`")
    if time_label is not None and not isinstance(time_label, str):
        raise TypeError(f"`time_label` must be a string, got {time_label!r}.")
    if hasattr(confidence, "item") and np.shape(confidence) == ():
        confidence = confidence.item()  # (a 0-d array)
    if confidence is not None and (
        isinstance(confidence, bool)
        or not isinstance(confidence, numbers.Real)
        or not 0.0 < confidence < 1.0
    ):
        raise ValueError(f"`confidence` must be a level in (0, 1), e.g. 0.95, got {confidence!r}.")
    times = t  # the sample times a timed model's FitResult is simulated at
    if t is None:
        step = Ts if Ts is not None else _model_dt(models)
        t = np.arange(T) * (1.0 if step is None else float(step))
        xlabel = "time (s)" if Ts is not None else "sample" if step is None else "time"
    else:
        t = _as_times(t, "t")
        if t.shape != (T,):
            raise ValueError(f"`t` must have shape (T,) = ({T},), got {t.shape}.")
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
            raise ValueError("`t` must hold finite, increasing sample times.")
        xlabel = "time"

    outputs = []  # a loop, not a comprehension: its warnings point at the caller's line
    bands = []  # each model's half-width of its confidence band, or None
    for i, m in enumerate(models):
        outputs.append(_model_output(i, m, u, z, n, times, Ts))
        bands.append(_band(m, u, z, n, times, confidence))
    fig, axes = _axes(ax, n_z, plt, (8.0, 0.6 + 2.6 * n_z))
    measured = np.isfinite(z[n:])  # missing samples are left out of the FIT
    # An output never sampled at an instant (one measured only in aggregate, an all-NaN
    # column) has no FIT: NaN in the legend, its model output still drawn.
    some = measured.any(axis=0)

    def fit_of(zhat):
        out = np.full(n_z, np.nan)
        if some.any():
            out[some] = np.asarray(
                metrics.fit_percent(z[n:, some], zhat[n:, some], measured[:, some])
            )
        return out

    fits = [fit_of(zhat) for zhat in outputs]
    # The head: where a FitResult's or a Prediction's initial state was estimated from;
    # for plain arrays and K-step predictions only the samples the FIT leaves out.
    estimated = any(isinstance(m, (FitResult, Prediction)) for m in models)
    head = "x0, not scored" if estimated else "not scored"
    for k, a in enumerate(axes):
        a.plot(t, z[:, k], color="k", lw=1.2, label="measured")
        for m, zhat, fit, label, band in zip(models, outputs, fits, labels, bands):
            shown = f"{fit[k]:.2f}" if abs(fit[k]) < 1e4 else f"{fit[k]:.3g}"
            (line,) = a.plot(t, zhat[:, k], lw=1.0, label=f"{label}: FIT {shown} %")
            if band is not None:
                lo, hi = zhat[:, k] - band[:, k], zhat[:, k] + band[:, k]
                a.fill_between(
                    t,
                    lo,
                    hi,
                    color=line.get_color(),
                    alpha=0.25,
                    lw=0,
                    label=f"{label}: {100 * confidence:g} % "
                    + ("prediction band" if isinstance(m, AheadPrediction) else "band"),
                )
        if any(b is not None for b in bands):  # (the axis the outputs' range, not a band's)
            values = np.concatenate([z[:, k], *(zhat[:, k] for zhat in outputs)])
            values = values[np.isfinite(values)]
            if values.size:
                low, high = float(values.min()), float(values.max())
                span = max(high - low, 1e-12 * max(abs(low), abs(high)), 1e-300)
                shown_low, shown_high = a.get_ylim()
                a.set_ylim(max(shown_low, low - span), min(shown_high, high + span))
        if n:
            a.axvspan(t[0], t[n], color="0.85", zorder=0, label=f"first {n} samples ({head})")
            a.axvline(t[n], color="0.4", lw=0.8, ls="--")
        a.set_ylabel(names[k])
        a.legend(fontsize=8, loc="best")
    axes[-1].set_xlabel(xlabel if time_label is None else time_label)
    simulated = not n and any(isinstance(m, FitResult) for m in models)
    axes[0].set_title(
        "Measured and model outputs"
        + (f" (x0 from the first {n} samples, FIT over the rest)" if n else "")
        + (" (FitResults simulated from their fitted x0)" if simulated else "")
    )
    if ax is None:
        fig.tight_layout()
    return fig


def _names(given, count, arg, thing, start, of=""):
    """`compare`'s names of its models or outputs: `given` checked (a string for one, or a
    sequence of `count` strings), or the defaults `thing` or `thing <start>`, ...."""
    if given is None:
        return [thing] if count == 1 else [f"{thing} {i + start}" for i in range(count)]
    names = [given] if isinstance(given, str) else given
    if not isinstance(names, (list, tuple)) or not all(isinstance(s, str) for s in names):
        raise TypeError(
            f"`{arg}` must be a string or a sequence of {count} strings (one per {thing}), "
            f"got {given!r}."
        )
    if len(names) != count:
        raise ValueError(
            f"`{arg}` must hold {count} names (one per {thing}{of}), got {list(names)}."
        )
    return list(names)


def _beyond(out):
    """ ", k beyond the joint band" for the k lags `out` marks (else "")."""
    k = int(np.sum(out))
    return f", {k} beyond the joint band" if k else ""


def resid(e, u=None, max_lag=25, *, confidence=0.99, tolerance=0.05, demean=True):
    """Plot the residual analysis of MATLAB's `resid`: the autocorrelation of the residuals
    and their cross-correlation with each input, with the confidence band, and the
    whiteness and independence verdicts in the title.

    The numbers are those of `oneshot_jax.metrics.residual_correlations` (definitions,
    bounds after Ljung, *System Identification*, Sec. 16.6, and verdicts there): one row
    per output, the autocorrelation over lags 0..max_lag in the first column, the
    cross-correlation with input j over lags -max_lag..max_lag in column j + 1. Points
    outside the band are drawn in red; the dashed lines are the joint band, which no lag
    of a verdict may leave.

    **Arguments:**

    - `e`: the residuals (T,), (T, n_z) or (N, T, n_z), NaN where missing, or a
        `FitResult` (its `residuals`, zhat - z on the fitted data; an output without
        residual samples, one measured only in aggregate, is left out, as the title
        says).
    - `u`: the inputs of the same record(s), (T,), (T, n_u) or (N, T, n_u); None: the
        autocorrelation only.
    - `max_lag`, `confidence`, `tolerance`, `demean`: as for `residual_correlations`.

    **Returns:**

    The matplotlib `Figure`.

    **Raises:**

    `ImportError` without matplotlib (install the `plot` extra); `ValueError` as
    `residual_correlations`.
    """
    plt = _pyplot()
    windows, skipped, names, stop = None, [], None, None
    if isinstance(e, FitResult):
        windows = e.window_starts
        if not e.success:
            stop = f"the fit did not succeed (status {e.status}): residuals of the returned point"
        e = np.asarray(e.residuals)
        # An output never sampled at an instant (one measured only in aggregate) has no
        # residual series: left out, and said so in the title.
        seen = np.sum(np.isfinite(e.reshape(-1, e.shape[-1])), axis=0) >= 2
        if seen.any() and not seen.all():
            skipped = [int(k) for k in np.flatnonzero(~seen)]
            names = [int(k) for k in np.flatnonzero(seen)]
            e = e[..., seen]
    try:
        rc = metrics.residual_correlations(
            e, u, max_lag, confidence=confidence, tolerance=tolerance, demean=demean
        )
    except ValueError as err:
        if windows is None or u is None:
            raise
        # A windowed fit's residuals are per window: the record's u does not match them.
        raise ValueError(
            f"{err} The result's residuals are per window ({len(windows)} windows, starting "
            "at `result.window_starts`): pass u cut the same way, or the residuals of "
            "`result.simulate` on the whole record."
        ) from err
    n_z = rc.auto.shape[1]
    names = list(range(n_z)) if names is None else names
    n_u = 0 if rc.cross is None else rc.cross.shape[2]
    fig, axes = plt.subplots(
        n_z, 1 + n_u, squeeze=False, figsize=(4.2 * (1 + n_u), 0.9 + 2.4 * n_z)
    )
    pct = f"{100 * confidence:g} %"

    def stems(a, lags, r, bound, joint, auto=False):
        a.axhspan(-bound, bound, color="C0", alpha=0.18, lw=0, label=f"{pct} confidence")
        a.axhline(joint, color="C0", lw=0.8, ls="--", label="joint band")
        a.axhline(-joint, color="C0", lw=0.8, ls="--")
        a.axhline(0.0, color="k", lw=0.6)
        a.vlines(lags, 0.0, r, color="C0", lw=1.0)
        out = (np.abs(r) > bound) & ~(auto & (lags == 0))  # r_e(0) = 1 is no test
        a.plot(lags[~out], r[~out], "o", color="C0", ms=3)
        a.plot(lags[out], r[out], "o", color="C3", ms=3.5)
        a.set_xlabel("lag (samples)")

    verdicts = []
    for i in range(n_z):
        lags = rc.lags[max_lag:]
        r_e = rc.auto[max_lag + 1 :, i]
        stems(axes[i, 0], lags, rc.auto[max_lag:, i], rc.bound[i], rc.joint_bound[i], auto=True)
        axes[i, 0].set_title(f"autocorrelation of e[{names[i]}]", fontsize=9)
        axes[i, 0].legend(fontsize=7, loc="upper right")
        peak = _beyond(np.abs(r_e) > rc.joint_bound[i])
        text = (
            f"e[{names[i]}]: {'white' if rc.white[i] else 'not white'} "
            f"({100 * rc.auto_outside[i]:.0f} % of lags outside{peak})"
        )
        for j in range(n_u):
            stems(
                axes[i, j + 1],
                rc.lags,
                rc.cross[:, i, j],
                rc.cross_bound[i, j],
                rc.cross_joint_bound[i, j],
            )
            axes[i, j + 1].axvline(0.0, color="0.5", lw=0.6, ls=":")
            axes[i, j + 1].set_title(f"cross-correlation of e[{names[i]}] and u[{j}]", fontsize=9)
        if n_u:
            worst = 100 * float(np.max(rc.cross_outside[i]))
            beyond = np.abs(rc.cross[max_lag:, i]) > rc.cross_joint_bound[i]
            peak = _beyond(beyond)
            text += (
                ", independent of past inputs"
                if rc.independent[i]
                else f", correlated with past inputs ({worst:.0f} % of lags outside{peak})"
            )
        verdicts.append(text)
    counts = np.unique(rc.n)
    samples = str(int(counts[0])) if len(counts) == 1 else "/".join(str(int(c)) for c in rc.n)
    if skipped:
        verdicts.append(f"e{skipped}: no residual samples (measured only in aggregate)")
    if stop:
        verdicts.append(stop)
    fig.suptitle(
        f"Residual analysis ({pct} bounds, n = {samples} samples)\n" + "\n".join(verdicts),
        fontsize=10,
    )
    fig.tight_layout()
    return fig


def _default_frequencies(models, continuous):
    """400 angular frequencies, log-spaced: up to the Nyquist frequency pi / dt of the
    discrete-time models (three decades below it), or a decade either side of the
    continuous-time poles' magnitudes."""
    if continuous:
        mags = np.concatenate([np.abs(np.linalg.eigvals(m.Ac)) for m in models])
        mags = mags[mags > 0]
        lo, hi = (0.1 * mags.min(), 10.0 * mags.max()) if mags.size else (0.01, 100.0)
    else:
        hi = min(np.pi / (1.0 if m.dt is None else m.dt) for m in models)
        lo = 1e-3 * hi
    return np.logspace(np.log10(lo), np.log10(hi), 400)


def bode(*models, w=None, continuous=False, labels=None, ax=None):
    """Bode plot of one or several linear models (MATLAB's `bode` of `linearize`'s
    model): the gain in dB and the phase in degrees of each input-output pair against the
    angular frequency, from `LinearModel.frequency_response`.

    **Arguments:**

    - `models`: `LinearModel`s (from `oneshot_jax.linearise` or `result.linearise`), with
        the same numbers of inputs and outputs.
    - `w`: the angular frequencies (n_w,), in radians per unit of the models' `dt` (per
        sample where `dt` is None); default 400 log-spaced ones up to the Nyquist
        frequency pi / dt (or a decade either side of the poles with `continuous`).
    - `continuous`: True: the continuous-time models (Ac, Bc) of ODE models.
    - `labels`: one name per model; default `"model"` or `"model 1"`, ....
    - `ax`: two matplotlib Axes (gain, phase); default a new figure.

    A pair whose response is zero (no path from the input to the output: |H| at the
    round-off of the other pairs' at every frequency) is not drawn; the legend says so.

    **Returns:** the matplotlib `Figure`.

    **Raises:** `TypeError` for a model that is not a `LinearModel`; `ValueError` for
    models of other sizes, models with and without `dt` together (their frequencies are
    per time unit and per sample), `continuous` without an ODE model's Ac, or
    frequencies that are not positive.
    """
    plt = _pyplot()
    if (
        len(models) == 1
        and isinstance(models[0], (list, tuple))
        and not isinstance(models[0], LinearModel)  # (itself a NamedTuple)
    ):
        models = tuple(models[0])
    if not models:
        raise ValueError("`models` is empty: pass at least one `LinearModel`.")
    for i, m in enumerate(models):
        if not isinstance(m, LinearModel):
            raise TypeError(
                f"`models[{i}]` must be a `LinearModel` (from `oneshot_jax.linearise`), got "
                f"{type(m).__name__}."
            )
    sizes = {(m.C.shape[0], m.B.shape[1]) for m in models}
    if len(sizes) != 1:
        raise ValueError(
            f"the models must have the same numbers of outputs and inputs, got {sorted(sizes)}."
        )
    n_z, n_u = sizes.pop()
    steps = {m.dt is None for m in models}
    if len(steps) > 1 and not continuous:
        raise ValueError(
            "`models` mix frequency units: a model without `dt` (a `Model` of its own step) "
            "has its response in radians per sample, one with `dt` (`Model.from_ode`) in "
            "radians per time unit; draw them on separate plots."
        )
    if continuous and any(m.Ac is None for m in models):
        raise ValueError(
            "`continuous=True` needs models built from an ODE (`Model.from_ode`): a model "
            "here has no Ac, Bc."
        )
    w = _default_frequencies(models, continuous) if w is None else frequencies(w, positive=True)
    labels = _names(labels, len(models), "labels", "model", start=1)
    fig, (gain, phase) = _axes(ax, 2, plt, (8.0, 6.0), "gain and phase")
    for m, label in zip(models, labels):
        H = m.frequency_response(w, continuous=continuous)
        finite = np.abs(H[np.isfinite(H)])
        # (a pair without a path from input to output: its H is round-off of the others')
        floor = 1e3 * np.finfo(np.float64).eps * (finite.max() if finite.size else 0.0)
        for i in range(n_z):
            for j in range(n_u):
                pair = "" if n_z * n_u == 1 else f" z[{i}] <- u[{j}]"
                if np.all(np.abs(H[:, i, j]) <= floor):
                    gain.plot([], [], label=f"{label}{pair}: no response (zero)")
                    continue
                with np.errstate(divide="ignore"):
                    gain.semilogx(w, 20 * np.log10(np.abs(H[:, i, j])), label=label + pair)
                phase.semilogx(w, np.degrees(np.unwrap(np.angle(H[:, i, j]))), label=label + pair)
    gain.set_ylabel("gain (dB)")
    phase.set_ylabel("phase (deg)")
    dt = {m.dt for m in models}
    per = "sample" if None in dt and not continuous else "time unit"
    phase.set_xlabel(f"angular frequency (rad per {per})")
    gain.legend(fontsize=8, loc="best")
    gain.set_title("Bode plot" + (" (continuous time)" if continuous else ""))
    if ax is None:
        fig.tight_layout()
    return fig
