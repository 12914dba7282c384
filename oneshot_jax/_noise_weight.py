"""`fit(weight="noise")`: the output weight Q estimated with theta, as MATLAB's
`nlgreyestOptions(OutputWeight="noise")`.

The covariance of a fit pools one noise level sigma^2 over the outputs (eq. (4)'s Q
weighs them): its standard errors are the Cramer-Rao bound only where Q is proportional
to the inverse of the noise covariance. With `weight="noise"` the fit alternates: fit
theta and x0 with Q, then set Q to the inverse of the residuals' covariance E^T E / n,
until Q settles (the relaxation algorithm of output-error estimation with an unknown
noise covariance, whose fixed point minimises det(E^T E / n): Ljung, *System
Identification*, 2nd ed., 1999, Section 7.3 and eq. (7.90)). Each round starts where the
last stopped, so its solve is short, and the fit's compiled program is reused.

Aggregated readings (`fit(aggregate=...)`, `_aggregate`) are observations too: each
`Aggregate`'s weights get a factor per round, the inverse mean square of its readings'
residuals, on the scale of Q (the readings of an output measured only in aggregate carry
its whole noise level), so that the covariance's one sigma^2 holds for them as well."""

import copy
import dataclasses
import warnings

import numpy as np

from ._aggregate import _per_record, record_times
from ._caller_warnings import unrecorded, warn
from ._results import RESULTS, is_success, name_of

# Rounds of the alternation at most, and the change of Q (relative, in the Frobenius
# norm, Q normalised to det Q = 1) at which it counts as settled.
NOISE_ROUNDS = 10
NOISE_RTOL = 1e-3


def _all_or_none(seen):
    """Whether every sample (a row of `seen`, (samples, n_z) bool) measures all outputs or
    none: then Q is the full inverse covariance (`noise_weight`)."""
    return bool((seen.all(axis=1) | ~seen.any(axis=1)).all())


def _output_scales(z, n_z):
    """Each output's largest magnitude over its finite samples (every record's), (n_z,):
    the scale of its round-off (`noise_weight`'s `scales`); 0 for an output without one."""
    records = z if isinstance(z, (list, tuple)) else [z]
    rows = [np.asarray(r, dtype=np.float64).reshape(-1, n_z) for r in records]
    a = np.abs(np.concatenate(rows)) if rows else np.zeros((0, n_z))
    return np.max(np.where(np.isfinite(a), a, 0.0), axis=0, initial=0.0)


# Residuals of an output whose root mean square is below this many units of round-off of
# its largest sample count as zero: the model fits it exactly, there is no noise level.
ROUND_OFF_UNITS = 64


def noise_weight(residuals, readings=(), scales=None):
    """Q from a fit's residuals: the inverse of E^T E / n over the samples (every record's,
    pooled) where every output is measured, (n_z, n_z), where every sample measures all
    outputs or none (a sample of none, such as the padding past the end of a shorter
    record, tells nothing and is left out); where some sample measures some outputs only,
    the diagonal 1 / (each output's mean squared residual over its samples), (n_z,).

    `readings`: one array per `Aggregate`, its readings' residuals times the square root
    of their given weights (1 where none is given; NaN for a reading that is missing or
    of weight 0); each gets a factor, 1 / their mean square, for its given weights. Q and
    the factors are normalised together so that the geometric mean of the noise levels
    they invert is 1 (det Q = 1 without readings: a fit ignores the weights' common scale;
    the loss keeps its size). An output without point samples (measured only in
    aggregate, or not at all) gets Q's entry 1, and an Aggregate without a reading that
    counts the factor 1: they have nothing to weigh.

    `scales`: each output's data scale (`_output_scales`), or None: an output whose
    residuals' root mean square is below `ROUND_OFF_UNITS` units of round-off (of the
    residuals' dtype) of its scale counts as all zero.

    **Returns:** `((Q, factors), None)`, or `(None, name)` where the residuals of `name`
    (an output, an Aggregate, or "the outputs" where nothing is measured) are all zero:
    no noise level to weigh by."""
    eps = np.finfo(np.result_type(np.asarray(residuals).dtype, np.float32)).eps
    e = np.asarray(residuals, dtype=np.float64)
    e = e.reshape(-1, e.shape[-1])
    n_z = e.shape[-1]
    seen = np.isfinite(e)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # (an output with no sample: NaN)
        var = np.nanmean(np.where(seen, e**2, np.nan), axis=0)
        levels = [np.nanmean(np.asarray(r, dtype=np.float64) ** 2) for r in readings]
    sampled = np.isfinite(var)
    floor = np.zeros(n_z) if scales is None else (ROUND_OFF_UNITS * eps * np.asarray(scales)) ** 2
    for j in range(n_z):
        if sampled[j] and var[j] <= floor[j]:
            return None, f"output {j}"
    counted = [bool(np.isfinite(level)) for level in levels]  # (some reading counts)
    for i, level in enumerate(levels):
        if counted[i] and level <= 0:
            return None, f"aggregate {i}"
    if not (sampled.any() or any(counted)):
        return None, "the outputs"
    logs = [np.log(level) for level, c in zip(levels, counted) if c]
    Q = None
    rows = seen.any(axis=1)  # (samples of no output: left out)
    if n_z > 1 and rows.any() and _all_or_none(seen):
        S = e[rows].T @ e[rows] / np.count_nonzero(rows)
        if np.linalg.cond(S) < 1e12:
            Q = np.linalg.inv(S)
            Q = 0.5 * (Q + Q.T)
            logs += [np.linalg.slogdet(S)[1] / n_z] * n_z
    if Q is None:
        Q = np.where(sampled, 1.0 / np.where(sampled, var, 1.0), np.nan)
        logs += list(np.log(var[sampled]))
    c = float(np.exp(np.mean(logs)))
    Q = np.where(np.isnan(Q), 1.0, c * Q)  # (an output without point samples: 1)
    return (Q, [c / level if n else 1.0 for level, n in zip(levels, counted)]), None


def _ratios(new, old):
    """The relative changes of the readings' factors."""
    return [abs(a - b) / b for a, b in zip(new, old, strict=True)]


def _change(new, old):
    new, old = np.asarray(new), np.asarray(old)
    if new.shape != old.shape:  # (one round full, the next diagonal: compare matrices)
        new = np.diag(new) if new.ndim == 1 else new
        old = np.diag(old) if old.ndim == 1 else old
    return float(np.linalg.norm(new - old) / np.linalg.norm(old))


def _reading_residuals(result, args):
    """Per `Aggregate` of `args["aggregate"]` (records in order, each record's in order),
    the residuals of its readings at `result` times the square root of their given
    weights (1 where none is given; NaN for a missing reading or one of weight 0): the
    fitted model simulated on each record (from its fitted x0) and aggregated
    (`Aggregate.predict`)."""
    u, t, model = args["u"], args["t"], args["model"]
    ragged = isinstance(u, (list, tuple))
    batched = ragged or np.ndim(u) == 3
    zhat = result.simulate(u, t=t if model.timed else None)[1]
    zhat = list(zhat) if batched else [zhat]
    lengths = [np.shape(z)[0] for z in zhat]
    times = record_times(model, t, batched, lengths)
    out = []
    for i, aggs in enumerate(_per_record(args["aggregate"], batched, len(zhat))):
        ti = None if times[i] is None else np.asarray(times[i], dtype=float)[: lengths[i]]
        for agg in aggs:
            w = np.ones(len(agg.values)) if agg.weight is None else agg.weight
            pred = np.asarray(agg.predict(np.asarray(zhat[i])[: lengths[i]], ti), np.float64)
            r = np.sqrt(w) * (pred - agg.values)
            out.append(np.where(w > 0, r, np.nan))
    return out


def _reweighted(aggregate, factors):
    """`aggregate` (an `Aggregate`, a list, or one entry per record) with each Aggregate's
    given weights (1 where none) times its factor, in `_reading_residuals`' order."""
    it = iter(factors)

    def one(agg):
        new = copy.copy(agg)
        w = np.ones(len(agg.values)) if agg.weight is None else agg.weight
        new.weight = w * next(it)
        return new

    def walk(a):
        if a is None:
            return None
        if isinstance(a, (list, tuple)):
            return [walk(b) for b in a]
        return one(a)

    return walk(aggregate)


def _identity(z):
    """Q = I in the form `noise_weight` will return for these outputs (records), so that
    the first fit and the next share one compiled program: (n_z, n_z) where every sample
    of every record measures every output or none, else the diagonal (n_z,) (a form that
    differs only costs a second compilation)."""
    records = list(z) if isinstance(z, (list, tuple)) else [z]
    arrays = [np.asarray(r, dtype=np.float64) for r in records]
    n_z = arrays[0].shape[-1]
    full = n_z > 1 and all(_all_or_none(np.isfinite(a).reshape(-1, n_z)) for a in arrays)
    return np.eye(n_z) if full else np.ones(n_z)


def fit_noise_weighted(fit, args):
    """`fit(**args)` with the weight estimated from the residuals (see the module
    docstring): from Q = I, at most `NOISE_ROUNDS` fits, each warm-started from the last
    (theta, and x0 where its shape is the one given; a multistart only in the first, whose
    `starts` and `best` the result keeps); the result of the last fit, whose Q the
    residuals reproduce to `NOISE_RTOL`, with `result.weight` that Q (None where it is
    the first fit's Q = I),
    `stop_info["noise_weight_rounds"]` the number of fits, and `num_steps` and
    `wall_time` those of all fits together.
    Only the returned fit's warnings are shown and kept (`FitResult.warnings`: not those
    of the rounds before it); a Q that has not settled after the last round, or residuals
    that give none, get a warning of their own."""
    given_x0 = np.shape(args["x0"])
    aggregate = args.get("aggregate")
    w, scales, used, change, rounds, result, first = None, [], [], np.inf, 0, None, None
    unsettled = False  # (the alternation ran its rounds, or ran away)
    steps, wall = 0, 0.0
    for rounds in range(1, NOISE_ROUNDS + 1):
        with warnings.catch_warnings(record=True) as caught, unrecorded():
            warnings.simplefilter("always")
            result = fit(**{**args, "weight": _identity(args["z"]) if w is None else w})
        steps, wall = steps + result.num_steps, wall + result.wall_time
        if first is None:  # (Q = I: as without a weight)
            first = result = dataclasses.replace(result, weight=None)
        if not np.isfinite(float(result.loss)):
            break
        used = scales  # (the readings' factors of this fit)
        readings = (
            ()
            if aggregate is None
            else _reading_residuals(result, {**args, "aggregate": aggregate})
        )
        n_z = np.shape(result.residuals)[-1]
        weights, empty = noise_weight(result.residuals, readings, _output_scales(args["z"], n_z))
        if weights is None:
            unsettled = w is not None  # (after a reweighting: its own weight ran away)
            last = "the given weights" if w is None else "the last estimated weights"
            caught.append(
                warnings.WarningMessage(
                    f"`weight='noise'`: the residuals of {empty} are all zero, "
                    "so there is no noise level to weigh it by (residuals at the round-off "
                    "of the data count as zero: the model fits them exactly); the result is "
                    f"that of the fit with {last}.",
                    UserWarning,
                    __file__,
                    0,
                )
            )
            break
        Q, factors = weights
        # (against the weights this fit used: Q = I and the readings' own in the first,
        # so that one output, whose Q is 1 whatever its residuals, takes one fit)
        used = scales or [1.0] * len(factors)
        before = _identity(args["z"]) if w is None else w
        change = max([_change(Q, before), *_ratios(factors, used)])
        if change <= NOISE_RTOL:
            break
        w, scales = Q, factors
        x0 = np.asarray(result.x0)
        args = {
            **args,
            "theta0": result.theta,
            "x0": x0 if x0.shape == given_x0 else args["x0"],
            "multistart": False,
        }
        if aggregate is not None:
            args["aggregate"] = _reweighted(aggregate, factors)
    else:
        unsettled = True
        caught.append(
            warnings.WarningMessage(
                f"`weight='noise'`: the weight had not settled after {NOISE_ROUNDS} fits "
                f"(its last relative change {change:.3g} > {NOISE_RTOL:g}); the result is "
                "that of the last fit.",
                RuntimeWarning,
                __file__,
                0,
            )
        )
    for c in caught:
        if c.filename == __file__ or str(c.message) in result.warnings:
            warn(c.message, c.category, stacklevel=3)  # (the result keeps it: `fit`'s record)
        else:  # (not the library's: shown, as without the weight, and not kept)
            warn(c.message, c.category, stacklevel=3, kept=False)
    # (whether a Q was estimated at all: not where the first fit's loss is not finite or
    # its residuals give none, as the warning says)
    estimated = w is not None or change <= NOISE_RTOL
    info = {**result.stop_info, "noise_weight_rounds": rounds}
    if not estimated:
        info["noise_weight_estimated"] = False
    if used:
        info["reading_weight_factors"] = [float(f) for f in used]
    reason = result.stop_reason
    if unsettled and is_success(reason):  # (a solution of the last weights only)
        info["solver_stop"] = name_of(reason)
        reason = RESULTS.noise_weight_unsettled
    result = dataclasses.replace(
        result, stop_reason=reason, stop_info=info, num_steps=steps, wall_time=wall
    )
    if first.starts is not None and result.starts is None:  # (the first fit's multistart)
        result = dataclasses.replace(result, starts=first.starts, best=first.best)
    return result
